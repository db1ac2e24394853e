"""Clutter the DTM lacks over a whole region: forest, a town, crops.

One tree is a track a few metres off the DTM, often within its triangulation error (a
five-frame track at 1800 m knows its height to ~5 m), so the per-track test of
:mod:`cdtm_graph.robust.mismatch` misses most of a forest; but a forest is many of them, all on
the same side, and together they pull the estimate down by a few metres while its
covariance, built for independent DTM errors, says one. Seen as a population, the
tracks' heights against the DTM are a mixture: ground (the DTM's own error about an offset
``b``, the estimate's vertical bias) and clutter (a share ``p`` at a common height ``H``
above it, spread ``tau``)::

    dh_t ~ (1 - p) N(b, s_t^2) + p N(b + H, s_t^2 + tau^2)

fitted by expectation-maximization. A clean flight fits no clutter (likelihood ratio
~2 against the ground alone); a 20% forest of 15-25 m trees gives p ~0.16, H ~15 m at a
likelihood ratio in the hundreds. Then each track has a posterior probability of being
on clutter (its share taken from its neighbourhood, so clutter stays where it is seen),
the likely ones are dropped, and the rest carry an expected offset: the frames they
constrain get it as a considered bias (:func:`considered_offsets`), a vertical variance
the estimate cannot remove, since a common vertical offset of the ground seen is
indistinguishable from the aircraft's altitude.

Pits and changed ground (``H < 0``) fit the same model; the neighbourhood test of
:mod:`cdtm_graph.robust.mismatch` catches those too.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from cdtm_graph.codes import Code
from cdtm_graph.results import StateCovariances, TerrainFindings
from cdtm_graph.robust.mismatch import MismatchSettings, TrackHeights, TrackJudgement, judge
from cdtm_graph.robust.neighbours import ball_sums
from factors.jit import njit

#: Clutter heights the expectation-maximization starts from (pits and objects), m.
_STARTS_M = (-30.0, -15.0, 15.0, 30.0)
#: Clutter is the minority of what a camera sees; where it covers more (a dense forest's
#: canopy), the tracks cannot say which surface the DTM describes.
MAX_SHARE = 0.45


@dataclass(frozen=True)
class ClutterSettings:
    """When the tracks' heights say clutter, and what is done about it.

    Attributes:
        min_tracks: fewer tracks say nothing about a population.
        max_sigma_m: tracks known worse than this carry nothing of the fit (their
            posterior is their neighbourhood's share).
        likelihood_ratio: ``2 log`` of the mixture's likelihood over the ground's alone
            the mixture must reach to be believed (clean flights: ~2; the robustness
            study's blocks and forest: hundreds; a mixture's ratio is not chi-square, so
            a wide margin).
        min_height_m: a clutter height below this is the DTM's own error, not clutter.
        min_share: a clutter share below this is a few stray tracks (wrong matches the
            other tests let by), not a population: on clean 150-300-frame logs a handful
            of tracks 40-60 m up reached likelihood ratios of 80-130 at a share of 0.03%.
        flag_offset_m: frames whose features may carry a vertical offset beyond this
            are flagged ``clutter``.
        radius_m: a track's clutter share is its neighbourhood's (this radius) mean
            posterior: a forest in one valley does not taint the next.
        drop_posterior: tracks more likely on clutter than this are dropped.
        iterations: of the expectation-maximization, at most (it stops once converged).
    """

    min_tracks: int = 50
    max_sigma_m: float = 40.0
    likelihood_ratio: float = 25.0
    min_height_m: float = 5.0
    min_share: float = 0.02
    radius_m: float = 600.0
    drop_posterior: float = 0.5
    flag_offset_m: float = 0.5
    iterations: int = 100


@dataclass(frozen=True)
class Clutter:
    """The mixture fitted to a set of tracks.

    Attributes:
        track_id: (T,) the tracks. posterior: (T,) each one's probability of being on
            clutter (0 everywhere when the fit is not :attr:`significant`).
        share: p, the clutter's share of the tracks. height_m: H, its height over the
            ground. spread_m: tau. ground_offset_m: b, where the ground tracks lie
            against the DTM at the estimate (its vertical bias, seen from below).
        likelihood_ratio: ``2 log`` of the mixture's likelihood over the ground's alone.
        significant: the fit is believed (ratio, height and number of tracks).
    """

    track_id: np.ndarray
    posterior: np.ndarray
    share: float
    height_m: float
    spread_m: float
    ground_offset_m: float
    likelihood_ratio: float
    significant: bool

    @classmethod
    def none(cls) -> Clutter:
        empty = np.zeros(0, np.int64)
        return cls(empty, np.zeros(0), 0.0, 0.0, 0.0, 0.0, 0.0, False)

    def likely(self, settings: ClutterSettings | None = None) -> np.ndarray:
        """Ids of the tracks more likely on clutter than ``drop_posterior``."""
        s = settings or ClutterSettings()
        return self.track_id[self.posterior > s.drop_posterior]

    def expected_offset_m(self, track_ids: np.ndarray) -> np.ndarray:
        """(n,) each track's expected height over the ground (posterior times H; 0 for
        tracks not in the fit)."""
        at = np.searchsorted(self.track_id, track_ids)
        at = np.clip(at, 0, max(self.track_id.size - 1, 0))
        known = (self.track_id.size > 0) & (self.track_id[at] == track_ids)
        return np.where(known, self.posterior[at] * self.height_m, 0.0) if known.size else \
            np.zeros(0)


def fit_clutter(heights: TrackHeights, settings: ClutterSettings | None = None) -> Clutter:
    """Fit the ground-and-clutter mixture to the tracks' heights (module docstring).

    Args:
        heights: the tracks (consistent ones: wrong matches left out by the caller).
        settings: the fit's settings.
    """
    s = settings or ClutterSettings()
    ids = heights.track_id
    none = Clutter(ids, np.zeros(ids.size), 0.0, 0.0, 0.0, 0.0, 0.0, False)
    used = (np.isfinite(heights.dh_m) & np.isfinite(heights.sigma_m)
            & (heights.sigma_m <= s.max_sigma_m))
    if used.sum() < s.min_tracks:
        return none
    dh, var = heights.dh_m[used], heights.sigma_m[used] ** 2
    # the ground alone: a weighted mean offset
    b0 = float(np.sum(dh / var) / np.sum(1.0 / var))
    ll0 = float(np.sum(_log_normal(dh - b0, var)))
    best = None
    for start in _STARTS_M:
        fit = _em(dh, var, start, s.iterations)
        if best is None or fit[0] > best[0]:
            best = fit
    assert best is not None
    ll, p, H, tau2, b = best
    ratio = 2.0 * (ll - ll0)
    significant = bool(ratio > s.likelihood_ratio and abs(H) >= s.min_height_m
                       and p >= s.min_share)
    if not significant:
        return Clutter(ids, np.zeros(ids.size), p, H, float(np.sqrt(tau2)), b, ratio, False)
    # each track's share from its neighbourhood's posteriors, then its own posterior
    dh_all = np.where(np.isfinite(heights.dh_m), heights.dh_m, b)
    var_all = np.where(used, heights.sigma_m**2, np.inf)
    first = _posterior(dh_all, var_all, np.full(ids.size, p), H, tau2, b)
    local = _neighbourhood_mean(heights.point_m, first, used, s.radius_m, p)
    posterior = _posterior(dh_all, var_all, local, H, tau2, b)
    return Clutter(ids, posterior, p, H, float(np.sqrt(tau2)), b, ratio, True)


def judge_with_clutter(heights: TrackHeights, sigma_h_m: float, mismatch: MismatchSettings,
           clutter: ClutterSettings | None) -> tuple[TrackJudgement, Clutter]:
    """Every view of a set of tracks: each alone and with its neighbourhood
    (:func:`cdtm_graph.robust.mismatch.judge`), and all of them as ground and clutter (the
    consistent ones; ``Clutter.none()`` without ``clutter`` settings)."""
    judged = judge(heights, sigma_h_m, mismatch)
    if clutter is None:
        return judged, Clutter.none()
    consistent = ~np.isin(heights.track_id, judged.inconsistent)
    return judged, fit_clutter(heights.subset(consistent), clutter)


def _log_normal(x: np.ndarray, var: np.ndarray) -> np.ndarray:
    return -0.5 * (x * x / var + np.log(2.0 * np.pi * var))


def _posterior(dh: np.ndarray, var: np.ndarray, p: np.ndarray, H: float, tau2: float,
               b: float) -> np.ndarray:
    """P(clutter | dh) per track; a track with infinite variance keeps its prior ``p``."""
    finite = np.isfinite(var)
    out = np.array(p, dtype=float)
    v = var[finite]
    l0 = np.log1p(-np.minimum(p[finite], 1 - 1e-12)) + _log_normal(dh[finite] - b, v)
    l1 = np.log(np.maximum(p[finite], 1e-300)) + _log_normal(dh[finite] - b - H, v + tau2)
    out[finite] = 1.0 / (1.0 + np.exp(np.clip(l0 - l1, -700, 700)))
    return out


def _em(dh: np.ndarray, var: np.ndarray, H: float, iterations: int
        ) -> tuple[float, float, float, float, float]:
    """Expectation-maximization from clutter height ``H``: (log-likelihood, p, H, tau^2,
    b)."""
    return _em_kernel(np.ascontiguousarray(dh, float), np.ascontiguousarray(var, float),
                      float(H), int(iterations), MAX_SHARE)


#: The EM's sums may be reordered (vectorized): ~25% off a fit, results to ~1e-14. Not
#: numba's full fastmath: no assumption that the data hold no NaN or infinity.
_REORDERED_SUMS = {"reassoc", "contract", "arcp"}


@njit(cache=True, fastmath=_REORDERED_SUMS)
def _em_kernel(dh: np.ndarray, var: np.ndarray, H: float, iterations: int, max_share: float
               ) -> tuple[float, float, float, float, float]:
    """:func:`_em`, compiled: one pass over the tracks per step (numpy's temporaries made
    the fit most of a judgement round)."""
    n = dh.size
    p, tau2, b = 0.05, 25.0, 0.0
    w = np.zeros(n)
    log_2pi = np.log(2.0 * np.pi)
    log_var = np.log(var)
    for _ in range(iterations):
        p0, H0, tau20, b0 = p, H, tau2, b
        # E step: each track's posterior of clutter (as _posterior, with a common p)
        log_p, log_q = np.log(max(p, 1e-300)), np.log1p(-min(p, 1 - 1e-12))
        for i in range(n):
            v1 = var[i] + tau2
            x0, x1 = dh[i] - b, dh[i] - b - H
            # (log 2 pi cancels in the difference)
            l0 = log_q - 0.5 * (x0 * x0 / var[i] + log_var[i])
            l1 = log_p - 0.5 * (x1 * x1 / v1 + np.log(v1))
            w[i] = 1.0 / (1.0 + np.exp(min(max(l0 - l1, -700.0), 700.0)))
        # M step. The ground is the majority: else the labels swap, and the ground goes
        # as clutter
        p = min(max(w.mean(), 1e-6), max_share)
        # b from the ground tracks and the clutter tracks alike (both sit on b)
        num, den = 0.0, 0.0
        for i in range(n):
            v1 = var[i] + tau2
            num += (1 - w[i]) * dh[i] / var[i] + w[i] * (dh[i] - H) / v1
            den += (1 - w[i]) / var[i] + w[i] / v1
        b = num / den
        num, den = 0.0, 0.0
        for i in range(n):
            v1 = var[i] + tau2
            num += w[i] * (dh[i] - b) / v1
            den += w[i] / v1
        H = num / max(den, 1e-12)
        # tau^2: the clutter's spread beyond the tracks' own (a moment step, floored)
        num = 0.0
        for i in range(n):
            x1 = dh[i] - b - H
            num += w[i] * (x1 * x1 - var[i])
        tau2 = max(num / max(w.sum(), 1e-9), 1.0)
        # converged: the clutter's expected count to half a track, the heights to a
        # centimetre, the spread to 0.01 m^2 (the log-likelihood is stationary in p: an
        # error of half a track in n moves it by ~ (n dp)^2 / (n p), well below the ratio's
        # threshold of 25)
        if (abs(p - p0) * n < 0.5 and abs(H - H0) < 1e-2 and abs(tau2 - tau20) < 1e-2
                and abs(b - b0) < 1e-2):
            break
    ll = 0.0
    log_p, log_q = np.log(p), np.log1p(-p)
    for i in range(n):
        v0, v1 = var[i], var[i] + tau2
        x0, x1 = dh[i] - b, dh[i] - b - H
        ll += np.logaddexp(log_q - 0.5 * (x0 * x0 / v0 + np.log(v0) + log_2pi),
                           log_p - 0.5 * (x1 * x1 / v1 + np.log(v1) + log_2pi))
    return ll, p, H, tau2, b


def _neighbourhood_mean(points: np.ndarray, values: np.ndarray, used: np.ndarray,
                        radius_m: float, default: float) -> np.ndarray:
    """(T,) the mean of ``values`` over the used tracks within ``radius_m`` of each
    track (horizontally); ``default`` where none is."""
    src = np.flatnonzero(used & np.isfinite(points[:, 0]))
    out = np.full(points.shape[0], default)
    if src.size == 0:
        return out
    where = np.flatnonzero(np.isfinite(points[:, 0]))
    sums, counts = ball_sums(points[where], points[src], values[src, None], radius_m)
    has = counts > 0
    out[where[has]] = sums[has, 0] / counts[has]
    return out


def considered_offsets(clutter: Clutter, key_a: Sequence[int], key_b: Sequence[int],
                       track_ids: Sequence[np.ndarray], n_frames: int) -> np.ndarray:
    """(K,) the vertical offset each frame's C-DTM features carry on average
    (:func:`frame_offset_m` of the factors that involve the frame).

    A common offset of the ground a frame sees moves its altitude by as much; the
    estimate cannot tell, so it is a considered bias of the frame's vertical position.
    """
    offsets = np.zeros(n_frames)
    if not clutter.significant:
        return offsets
    by_frame: dict[int, list[np.ndarray]] = {}
    for a, b, ids in zip(key_a, key_b, track_ids):
        for k in (int(gtsam.Symbol(a).index()), int(gtsam.Symbol(b).index())):
            by_frame.setdefault(k, []).append(ids)
    for k, ids_of_frame in by_frame.items():
        offsets[k] = frame_offset_m(clutter, ids_of_frame)
    return offsets


def frame_offset_m(clutter: Clutter, track_ids: Sequence[np.ndarray]) -> float:
    """The mean expected clutter height of these features (the tracks of a frame's
    factors, one array a factor): the vertical offset the frame's fix carries; 0 without
    clutter or features."""
    n = sum(ids.size for ids in track_ids)
    if not clutter.significant or n == 0:
        return 0.0
    return sum((float(np.sum(clutter.expected_offset_m(ids))) for ids in track_ids),
               0.0) / n


def with_vertical_bias(covariances: StateCovariances, world_T_body: np.ndarray,
                       offset_m: np.ndarray) -> StateCovariances:
    """The covariances with each frame's considered vertical offset (K,) added to its
    position's world-up variance."""
    up = np.zeros((offset_m.size, 3, 3))
    up[:, 2, 2] = offset_m**2
    return covariances.with_position_added(world_T_body, up)


def findings(clutter: Clutter, offsets_m: np.ndarray) -> TerrainFindings:
    """The report's summary of a clutter fit and the offsets it left."""
    return TerrainFindings(clutter.significant, clutter.share, clutter.height_m,
                           clutter.spread_m, clutter.ground_offset_m,
                           clutter.likelihood_ratio, offsets_m)


def clutter_flags(offsets_m: np.ndarray, settings: ClutterSettings) -> dict[int, list[str]]:
    """``{k: [Code.CLUTTER]}`` for the frames whose considered offset passes the flag."""
    return {int(k): [Code.CLUTTER] for k in np.flatnonzero(offsets_m > settings.flag_offset_m)}
