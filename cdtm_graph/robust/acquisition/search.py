"""The search: heading profile, terrain correlation, refinement of the modes, decision."""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import CameraConfig
from cdtm_graph.geometry import so3_exp
from cdtm_graph.robust.acquisition.cloud import Cloud, best_over_headings, make_cloud, track_costs
from cdtm_graph.robust.acquisition.refine import Features, Refined, Refiner, pair_features
from cdtm_graph.robust.acquisition.settings import AcquisitionSettings
from cdtm_graph.robust.acquisition.window import (
    AcquisitionFrame,
    Correction,
    Problem,
    SearchPrior,
    build_window,
)


class FixVerdict(enum.Enum):
    """What the search concluded."""

    ACQUIRED = "acquired"              # one fix, clearly better than every other
    AMBIGUOUS = "ambiguous"            # several fixes fit about equally well
    NO_INFORMATION = "no_information"  # the data cannot place the window (flat, too few)
    AT_EDGE = "at_edge"                # the best fix leaves the searched region: the
    #                                    truth may lie outside the prior


@dataclass(frozen=True)
class Hypothesis:
    """One candidate fix after refinement.

    Attributes:
        correction: what to apply to the first state.
        cost: robust C-DTM cost of the window at the fix (sum over features of the
            whitened squared residual, truncated).
        inlier_fraction: features within the truncation.
        separation_z: Vuong z of the best fix against this one (0 for the best itself):
            how many standard errors the best fits better.
        prior_sigmas: the fix's horizontal distance from the prior mean, in prior sigmas
            (Mahalanobis).
        search_cost: its point-cloud cost in the offset search (before refinement).
    """

    correction: Correction
    cost: float
    inlier_fraction: float
    separation_z: float
    prior_sigmas: float
    search_cost: float

    @property
    def offset_world_m(self) -> np.ndarray:
        """(3,) the first position's move."""
        return self.correction.translation_world_m


@dataclass(frozen=True)
class SearchRegion:
    """What :func:`acquire` searched.

    Attributes:
        half_width_m: (2,) half-widths of the offset grid in x, y (its ellipse inside).
        offset_step_m: the finest grid spacing. n_offsets: offsets scored per searched
            heading (a grid of twice the step over the ellipse, the step around the best).
        heading_range_deg: (low, high) of the heading profile; heading_step_deg its step.
        search_headings_deg: the headings whose offsets were scored.
        n_frames, n_tracks, n_features: the window's frames, tracks with two or more
            sightings, and C-DTM features (pairs of sightings) in the refinement.
    """

    half_width_m: tuple[float, float]
    offset_step_m: float
    n_offsets: int
    heading_range_deg: tuple[float, float]
    heading_step_deg: float
    search_headings_deg: tuple[float, ...]
    n_frames: int
    n_tracks: int
    n_features: int


@dataclass(frozen=True)
class AcquisitionResult:
    """The verdict, the ranked fixes and what was searched.

    Attributes:
        verdict: ACQUIRED, AMBIGUOUS, NO_INFORMATION or AT_EDGE.
        hypotheses: refined fixes, best first (empty for NO_INFORMATION).
        reason: one line saying why.
        searched: the region and data.
        time_s: wall time of the search.
        information_z: how many standard errors the best offset of the terrain search
            beat a typical one by (NaN if the search did not get that far).
    """

    verdict: FixVerdict
    hypotheses: tuple[Hypothesis, ...]
    reason: str
    searched: SearchRegion
    time_s: float
    information_z: float = float("nan")

    @property
    def correction(self) -> Correction | None:
        """The fix to apply: the best hypothesis when ACQUIRED, else None."""
        if self.verdict is FixVerdict.ACQUIRED:
            return self.hypotheses[0].correction
        return None


# --------------------------------------------------------------------------- the test


def needs_acquisition(position_covariance_world: np.ndarray, heading_sigma_rad: float,
                      settings: AcquisitionSettings | None = None) -> bool:
    """Whether the prior is wider than the smoothers pull in: search before refining.

    True when the ``n_sigma`` ellipse of the horizontal position reaches farther than
    ``pull_in_m``, or ``n_sigma`` heading sigmas exceed ``pull_in_heading_deg``.

    Args:
        position_covariance_world: (3, 3) position covariance (world, m^2) of the prior
            or of the current estimate after a long gap.
        heading_sigma_rad: 1-sigma heading error.
        settings: ``n_sigma`` and the pull-in.
    """
    settings = settings or AcquisitionSettings()
    P = np.asarray(position_covariance_world, dtype=float)[:2, :2]
    # the larger eigenvalue of the symmetric 2x2, closed form (asked every frame)
    half_trace, half_diff = 0.5 * (P[0, 0] + P[1, 1]), 0.5 * (P[0, 0] - P[1, 1])
    largest = half_trace + math.hypot(half_diff, 0.5 * (P[0, 1] + P[1, 0]))
    reach_m = settings.n_sigma * math.sqrt(max(float(largest), 0.0))
    reach_deg = settings.n_sigma * math.degrees(heading_sigma_rad)
    # (a prior exactly at the pull-in, e.g. 50 m at 3 sigma, needs no search: round-off
    # in the eigenvalues must not decide)
    slack = 1.0 + 1e-9
    return (reach_m > settings.pull_in_m * slack
            or reach_deg > settings.pull_in_heading_deg * slack)


def separation_z(costs_a: np.ndarray, costs_b: np.ndarray) -> float:
    """How many standard errors fix a fits better than fix b, from per-unit robust costs.

    Two tests on ``d_t = cost_b,t - cost_a,t`` over independent units (tracks), the costs
    being -2 log-likelihoods up to a constant; the weaker counts:

    * Vuong's (1989) test for non-nested models: ``sum d / (sqrt(n) sd(d))`` is
      asymptotically N(0, 1) when both fit equally well. It asks that the gain be
      consistent across tracks (a few tracks cannot carry it), but it is blind to scale:
      two fixes whose costs differ by round-off in the same direction score high.
    * The likelihood ratio itself (Wilks): ``sum d`` against chi-square(1), i.e.
      ``sqrt(sum d)`` sigmas; nearly equal fits (flat ground) score near 0.

    Returns:
        ``min(Vuong z, sqrt(sum d))``; 0 when a fits no better than b.
    """
    d = np.asarray(costs_b, dtype=float) - np.asarray(costs_a, dtype=float)
    gain = float(d.sum())
    sd = float(np.std(d))
    if d.size < 2 or sd == 0.0 or gain <= 0.0:
        return 0.0
    return min(gain / (math.sqrt(d.size) * sd), math.sqrt(gain))


# --------------------------------------------------------------------------- acquire


def _inside(prior: SearchPrior, n_sigma: float, offsets: np.ndarray) -> np.ndarray:
    """(M,) whether each horizontal offset (M, 2) lies in the prior's n-sigma ellipse."""
    P_inv = np.linalg.inv(np.asarray(prior.position_covariance_world, dtype=float)[:2, :2])
    return np.einsum("mi,ij,mj->m", offsets, P_inv, offsets) <= n_sigma ** 2


def _offset_grid(prior: SearchPrior, n_sigma: float, step: float):
    """A grid of spacing ``step`` over the prior's n-sigma ellipse: ``ox`` (nx,), ``oy``
    (ny,), which offsets lie inside (nx, ny), and the half-widths (m)."""
    P = np.asarray(prior.position_covariance_world, dtype=float)[:2, :2]
    half = n_sigma * np.sqrt(np.diag(P))
    nx, ny = (int(math.floor(h / step)) for h in half)
    ox = np.arange(-nx, nx + 1) * step
    oy = np.arange(-ny, ny + 1) * step
    grid = np.stack(np.meshgrid(ox, oy, indexing="ij"), axis=-1)
    inside = _inside(prior, n_sigma, grid.reshape(-1, 2)).reshape(grid.shape[:2])
    return ox, oy, inside, (float(half[0]), float(half[1]))


def _local_minima(cost: np.ndarray, ox: np.ndarray, oy: np.ndarray, step: float,
                  radius_m: float, k: int) -> list[tuple[int, int]]:
    """Indices of the ``k`` lowest local minima of a grid at least ``radius_m`` apart."""
    from scipy.ndimage import minimum_filter  # (only when a search runs: 0.05 s an import)

    size = 2 * max(1, int(round(radius_m / step))) + 1
    local = (cost == minimum_filter(cost, size=size, mode="constant", cval=np.inf))
    local &= np.isfinite(cost)
    ii, jj = np.nonzero(local)
    chosen: list[tuple[int, int]] = []
    for n in np.argsort(cost[ii, jj], kind="stable"):
        i, j = int(ii[n]), int(jj[n])
        if all(math.hypot(ox[i] - ox[a], oy[j] - oy[b]) >= radius_m for a, b in chosen):
            chosen.append((i, j))
            if len(chosen) == k:
                break
    return chosen


@dataclass(frozen=True)
class _Mode:
    """An offset of the terrain search: its cost, which cloud (heading) and vertical
    offset gave it."""

    cost: float
    offset_xy: np.ndarray
    cloud: Cloud
    vertical_m: float


def _heading_band(problem: Problem, headings: np.ndarray, clouds: list[Cloud],
                  best: int) -> np.ndarray:
    """The headings whose offsets are searched: every ``search_heading_step_deg`` from the
    best over those the rays do not reject, and over those an error of the velocity
    allows (the rays see the heading against the velocity's direction: an error of
    ``n_sigma`` velocity sigmas turns it by that over the speed)."""
    s = problem.settings
    plausible = [h for h, c in zip(headings, clouds)
                 if separation_z(clouds[best].ray_costs, c.ray_costs) < s.separation_z]
    speed = float(np.linalg.norm(problem.v0[:2]))
    slack = s.n_sigma * problem.prior.velocity_sigma_mps / speed if speed > 0 else math.inf
    lo = max(min(min(plausible), headings[best] - slack), headings[0])
    hi = min(max(max(plausible), headings[best] + slack), headings[-1])
    h_step = math.radians(s.search_heading_step_deg)
    return headings[best] + np.arange(math.ceil((lo - headings[best]) / h_step - 1e-9),
                                      math.floor((hi - headings[best]) / h_step + 1e-9)
                                      + 1) * h_step


def _terrain_modes(problem: Problem, clouds: list[Cloud], step: float
                   ) -> tuple[list[_Mode], _Mode | None, int]:
    """Terrain correlation over the prior's ellipse: a grid of twice ``step`` first, then
    ``step`` around its best local minima.

    Returns:
        Up to ``max_modes`` modes, best first, ``merge_radius_m`` apart; the typical offset
        (the median cost of the coarse grid; None if no offset is over the DTM); and the
        number of offsets scored per heading.
    """
    s, prior = problem.settings, problem.prior
    cx, cy, inside, _ = _offset_grid(prior, s.n_sigma, 2 * step)
    grid = np.stack(np.meshgrid(cx, cy, indexing="ij"), axis=-1)
    coarse = np.full(inside.shape, np.inf)
    which = np.zeros(inside.shape, dtype=np.int64)
    coarse[inside], which[inside], _ = best_over_headings(problem, clouds, grid[inside])
    n_scored = int(inside.sum())
    finite = np.flatnonzero(np.isfinite(coarse.ravel()))
    if finite.size == 0:
        return [], None, n_scored
    median = np.unravel_index(finite[np.argsort(coarse.ravel()[finite])[finite.size // 2]],
                              coarse.shape)
    typical = _Mode(float(coarse[median]), grid[median], clouds[which[median]], np.nan)

    peaks = _local_minima(coarse, cx, cy, 2 * step, s.merge_radius_m, 3 * s.max_modes)
    local = np.arange(-2, 3) * step  # one coarse step around each peak
    patch = np.stack(np.meshgrid(local, local, indexing="ij"), axis=-1).reshape(-1, 2)
    offsets = (grid[tuple(np.array(peaks).T)][:, None, :] + patch[None]).reshape(-1, 2)
    peak_of = np.repeat(np.arange(len(peaks)), len(patch))
    ok = _inside(prior, s.n_sigma, offsets)
    offsets, peak_of = offsets[ok], peak_of[ok]
    fine, f_which, f_vertical = best_over_headings(problem, clouds, offsets)
    n_scored += offsets.shape[0]
    candidates = []
    for p in range(len(peaks)):
        rows = np.flatnonzero(peak_of == p)
        r = rows[np.argmin(fine[rows])]
        candidates.append(_Mode(float(fine[r]), offsets[r], clouds[f_which[r]],
                                float(f_vertical[r])))
    modes: list[_Mode] = []
    for m in sorted(candidates, key=lambda m: m.cost):
        if len(modes) < s.max_modes and all(
                np.linalg.norm(m.offset_xy - k.offset_xy) >= s.merge_radius_m for k in modes):
            modes.append(m)
    return modes, typical, n_scored


def _refine_modes(problem: Problem, features: Features, modes: list[_Mode]
                  ) -> list[Hypothesis]:
    """Each mode refined with the C-DTM factors, one per basin (modes that converged
    within half a merge radius of a better one are that one), ranked, each scored
    against the best (:func:`separation_z`, per track)."""
    s = problem.settings
    refiner = Refiner(problem, features)
    refined: list[tuple[Refined, float]] = []
    for m in modes:
        guess = Correction(so3_exp(np.array([0.0, 0.0, m.cloud.heading_rad])),
                           np.r_[m.offset_xy, m.vertical_m], np.zeros(3))
        refined.append((refiner.refine(guess), m.cost))
    refined.sort(key=lambda r: r[0].cost)
    kept: list[tuple[Refined, float]] = []
    for r, search_cost in refined:
        if all(np.linalg.norm(r.correction.translation_world_m[:2]
                              - k.correction.translation_world_m[:2]) >= 0.5 * s.merge_radius_m
               for k, _ in kept):
            kept.append((r, search_cost))
    n_tracks = problem.window.n_tracks
    best = np.bincount(features.track, kept[0][0].feature_costs, minlength=n_tracks)
    P_inv = np.linalg.inv(problem.prior.position_covariance_world[:2, :2])
    hypotheses = []
    for n, (r, search_cost) in enumerate(kept):
        tracks = np.bincount(features.track, r.feature_costs, minlength=n_tracks)
        offset = r.correction.translation_world_m[:2]
        hypotheses.append(Hypothesis(
            r.correction, r.cost, float(np.mean(r.feature_costs < problem.tau ** 2)),
            0.0 if n == 0 else separation_z(best, tracks),
            float(math.sqrt(offset @ P_inv @ offset)), search_cost))
    return hypotheses


def _describe(h: Hypothesis) -> str:
    x, y, z = h.offset_world_m
    return f"({x:.0f}, {y:.0f}, {z:.0f}) m, heading {h.correction.heading_deg:+.2f} deg"


def acquire(frames: Sequence[AcquisitionFrame], camera: CameraConfig, dtm: Dtm,
            prior: SearchPrior, settings: AcquisitionSettings | None = None
            ) -> AcquisitionResult:
    """Search the prior for the fix that makes the window's features agree with the DTM.

    Args:
        frames: the first frames of the flight (or the frames after a gap), in time
            order, with their dead-reckoned poses: a few seconds of flight with some
            hundreds of tracks (the issue's flight: 6 frames at 1 fps, ~200 tracks).
        camera: intrinsics, pixel noise and mounting.
        dtm: the terrain.
        prior: the spread of the first state around ``frames[0].world_T_body``.
        settings: search settings.

    Returns:
        The verdict, the refined fixes ranked, and what was searched.

    Raises:
        FlightLogError: inconsistent frames (fewer than two, time order, shapes,
            repeated track ids in a frame).
    """
    start = time.perf_counter()
    s = settings or AcquisitionSettings()
    window = build_window(frames, camera)
    problem = Problem(window, camera, dtm, prior, s)
    step = float(s.offset_step_m or dtm.grid_spacing_m)

    # 1. Heading profile: how well the rays agree under each heading.
    n = int(math.floor(s.n_sigma * math.degrees(prior.heading_sigma_rad) / s.heading_step_deg))
    headings = np.radians(np.arange(-n, n + 1) * s.heading_step_deg)
    clouds = [make_cloud(problem, float(h)) for h in headings]
    best = int(np.argmin([c.ray_costs.sum() for c in clouds]))
    half = s.n_sigma * np.sqrt(np.diag(prior.position_covariance_world)[:2])
    region = SearchRegion((float(half[0]), float(half[1])), step, 0,
                          (float(np.degrees(headings[0])), float(np.degrees(headings[-1]))),
                          s.heading_step_deg, (), len(frames), window.n_tracks, 0)

    z = float("nan")

    def done(verdict: FixVerdict, reason: str, hypotheses: Sequence[Hypothesis] = ()
             ) -> AcquisitionResult:
        return AcquisitionResult(verdict, tuple(hypotheses), reason, region,
                                 time.perf_counter() - start, z)

    n_points = int(clouds[best].valid.sum())
    if n_points < s.min_tracks:
        return done(FixVerdict.NO_INFORMATION,
                    f"{n_points} tracks triangulate (of {window.n_tracks} seen twice or more "
                    f"in {len(frames)} frames), expected at least {s.min_tracks}")

    # 2-3. Terrain correlation under the headings the rays leave open.
    search_headings = _heading_band(problem, headings, clouds, best)
    modes, typical, n_offsets = _terrain_modes(
        problem, [make_cloud(problem, float(h)) for h in search_headings], step)
    region = replace(region, n_offsets=n_offsets,
                     search_headings_deg=tuple(float(np.degrees(h)) for h in search_headings))
    if typical is None:
        return done(FixVerdict.NO_INFORMATION,
                    "no offset of the search region puts the window's points over the DTM")

    # 4. Does the terrain say anything? The best offset against a typical one.
    z = separation_z(track_costs(problem, modes[0].cloud, modes[0].offset_xy),
                     track_costs(problem, typical.cloud, typical.offset_xy))
    if z < s.information_z:
        return done(FixVerdict.NO_INFORMATION,
                    f"the best offset fits the DTM no better than a typical one ({z:.1f} < "
                    f"{s.information_z:g} standard errors): the terrain under the window is "
                    "too flat or too unlike the DTM")

    # 5-6. Refine the modes with the C-DTM factors; the best against every other.
    features = pair_features(window)
    region = replace(region, n_features=features.n)
    hypotheses = _refine_modes(problem, features, modes)
    rivals = [h for h in hypotheses[1:] if h.separation_z < s.separation_z]
    if rivals:
        listed = "; ".join(f"{_describe(h)} (z {h.separation_z:.1f})"
                           for h in [hypotheses[0], *rivals])
        return done(FixVerdict.AMBIGUOUS, f"{len(rivals) + 1} fixes fit about equally well "
                    f"(best first, offsets from the prior mean): {listed}", hypotheses)
    if hypotheses[0].prior_sigmas > s.n_sigma:
        return done(FixVerdict.AT_EDGE,
                    f"the best fix, {_describe(hypotheses[0])} from the prior mean, lies "
                    f"{hypotheses[0].prior_sigmas:.1f} sigmas out, past the {s.n_sigma:g}-sigma "
                    "region searched: the truth may lie outside the prior", hypotheses)
    runner_up = (f"the next fix is {hypotheses[1].separation_z:.1f} standard errors worse"
                 if len(hypotheses) > 1 else "no other mode")
    return done(FixVerdict.ACQUIRED,
                f"fix at {_describe(hypotheses[0])} from the prior mean; {runner_up}",
                hypotheses)
