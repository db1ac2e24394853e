"""Wrong matches before the graph: each frame pair's features against the epipolar geometry.

Between two frames the IMU knows the relative rotation to a fraction of a pixel (a gyro
integrated over a second), and the translation's direction to about a degree (the
velocity's uncertainty over the baseline). A wrong match (the tracker locked onto
something else) lands anywhere in the image and almost never on its epipolar line, so
the epipolar constraint ``q_b . (t x R q_a) = 0`` rejects it before it can pull the
optimizer (the consistency check the paper's conclusion suggests). With the rotation
fixed, one translation direction is fixed by two features: a two-point RANSAC finds the
direction most features agree with, the IMU's own direction among the hypotheses.

The residual is the Sampson distance in normalized image units, compared with both
observations' pixel noise: for an inlier ``(d / sigma)^2`` is chi-square with one degree
of freedom.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from factors.jit import njit

#: Inlier test: chi-square(1) at 99.9% on the Sampson distance in sigmas.
CHI2_1DOF_999 = 10.827566170662733


@dataclass(frozen=True)
class EpipolarSettings:
    """How a pair's features are checked against the epipolar constraint.

    Attributes:
        hypotheses: two-point RANSAC draws per pair (with 30% wrong matches, 13 draws
            find an all-inlier pair with probability 0.999; a pair costs microseconds).
        min_parallax_sigmas: below this translation parallax (the baseline's angle seen
            from the ground, in units of the pixel noise) the constraint says nothing
            about a feature's position along the line: the pair is not checked.
        gate: squared Sampson distance, in sigmas, an inlier must pass.
        seed: of the RANSAC draws (repeatable runs).
    """

    hypotheses: int = 64
    min_parallax_sigmas: float = 20.0
    gate: float = CHI2_1DOF_999
    seed: int = 0


@dataclass(frozen=True)
class EpipolarCheck:
    """The verdict on one pair's features.

    Attributes:
        inlier: (n,) features consistent with the epipolar geometry.
        t_dir_b: (3,) the translation direction found (camera a's centre seen from
            camera b, unit), or the IMU's when the pair was not checked.
        checked: False when the parallax was too small to judge (every feature passes).
        angle_to_prior_rad: angle between the direction found and the IMU's.
    """

    inlier: np.ndarray
    t_dir_b: np.ndarray
    checked: bool
    angle_to_prior_rad: float


@njit(cache=True, inline="always")
def _sampson_terms(q_a: np.ndarray, q_b: np.ndarray, R_ba: np.ndarray) -> np.ndarray:
    """(n, 12) per feature, what the Sampson distance of ``q_b^T [t]x R q_a = 0`` needs of
    it for any direction t: ``R q_a``, ``R q_a x q_b`` and ``R_col0 x q_b``, ``R_col1 x
    q_b`` (so that ``q_b . (t x R q_a) = t . (R q_a x q_b)`` and the first two entries of
    ``E^T q_b = R^T (q_b x t)`` are ``t . (R_col x q_b)``)."""
    n = q_a.shape[0]
    out = np.empty((n, 12))
    for i in range(n):
        b0, b1, b2 = q_b[i, 0], q_b[i, 1], q_b[i, 2]
        r0 = R_ba[0, 0] * q_a[i, 0] + R_ba[0, 1] * q_a[i, 1] + R_ba[0, 2] * q_a[i, 2]
        r1 = R_ba[1, 0] * q_a[i, 0] + R_ba[1, 1] * q_a[i, 1] + R_ba[1, 2] * q_a[i, 2]
        r2 = R_ba[2, 0] * q_a[i, 0] + R_ba[2, 1] * q_a[i, 1] + R_ba[2, 2] * q_a[i, 2]
        out[i, 0], out[i, 1], out[i, 2] = r0, r1, r2
        out[i, 3], out[i, 4], out[i, 5] = r1 * b2 - r2 * b1, r2 * b0 - r0 * b2, r0 * b1 - r1 * b0
        for col in range(2):
            c0, c1, c2 = R_ba[0, col], R_ba[1, col], R_ba[2, col]
            out[i, 6 + 3 * col] = c1 * b2 - c2 * b1
            out[i, 7 + 3 * col] = c2 * b0 - c0 * b2
            out[i, 8 + 3 * col] = c0 * b1 - c1 * b0
    return out


@njit(cache=True)
def _sampson_kernel(terms: np.ndarray, t: np.ndarray, limit: float, d2: np.ndarray,
                    counts: np.ndarray, costs: np.ndarray) -> None:
    """Squared Sampson distances of ``q_b^T E q_a = 0``, E = [t]x R, normalized units, of
    every feature (its :func:`_sampson_terms`) for every direction t (h, 3): into ``d2``
    (h, n) if it has h rows, and each direction's inlier count and MSAC cost (``d2``
    capped at ``limit``)."""
    n, h = terms.shape[0], t.shape[0]
    keep = d2.shape[0] == h
    for j in range(h):
        t0, t1, t2 = t[j, 0], t[j, 1], t[j, 2]
        count, cost = 0, 0.0
        for i in range(n):
            x = terms[i]
            e0 = t1 * x[2] - t2 * x[1]  # E q_a = t x (R q_a), first two entries
            e1 = t2 * x[0] - t0 * x[2]
            f0 = t0 * x[6] + t1 * x[7] + t2 * x[8]  # E^T q_b, first two entries
            f1 = t0 * x[9] + t1 * x[10] + t2 * x[11]
            num = t0 * x[3] + t1 * x[4] + t2 * x[5]
            value = num * num / max(e0 * e0 + e1 * e1 + f0 * f0 + f1 * f1, 1e-300)
            if keep:
                d2[j, i] = value
            if value < limit:
                count += 1
                cost += value
            else:
                cost += limit
        counts[j] = count
        costs[j] = cost


@functools.lru_cache(maxsize=256)
def _picks(seed: int, n: int, hypotheses: int) -> np.ndarray:
    """(hypotheses, 2) the RANSAC draws for a pair of n features (repeatable runs; a
    generator made per pair cost as much as the scoring)."""
    picks = np.random.default_rng(seed).integers(0, n, (hypotheses, 2))
    picks.flags.writeable = False
    return picks


@njit(cache=True)
def _ransac(q_a: np.ndarray, q_b: np.ndarray, R_ba: np.ndarray, prior: np.ndarray,
            picks: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """The translation direction most features agree with (two-point hypotheses from
    ``picks``, the IMU's ``prior`` first), refined on its inliers; and the inliers."""
    # (element by element throughout: numba's array expressions and slice stores cost
    # seconds of compilation, and no run time here)
    n = q_a.shape[0]
    terms = _sampson_terms(q_a, q_b, R_ba)
    # each feature's epipolar plane normal q_b x R q_a; t must be perpendicular to every
    # inlier's
    normals = np.empty((n, 3))
    for i in range(n):
        normals[i, 0], normals[i, 1], normals[i, 2] = -terms[i, 3], -terms[i, 4], -terms[i, 5]
    candidates = np.empty((picks.shape[0] + 1, 3))
    candidates[0, 0], candidates[0, 1], candidates[0, 2] = prior[0], prior[1], prior[2]
    h = 1
    for j in range(picks.shape[0]):
        a, b = picks[j, 0], picks[j, 1]
        c0 = normals[a, 1] * normals[b, 2] - normals[a, 2] * normals[b, 1]
        c1 = normals[a, 2] * normals[b, 0] - normals[a, 0] * normals[b, 2]
        c2 = normals[a, 0] * normals[b, 1] - normals[a, 1] * normals[b, 0]
        norm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if norm > 1e-12:
            # the sign of t: the one closer to the IMU's (a direction and its opposite
            # fit alike)
            if c0 * prior[0] + c1 * prior[1] + c2 * prior[2] < 0:
                norm = -norm
            candidates[h, 0], candidates[h, 1], candidates[h, 2] = c0 / norm, c1 / norm, c2 / norm
            h += 1
    candidates = candidates[:h]
    # every hypothesis scored: inliers and MSAC cost (ties go to the tighter fit)
    counts, costs = np.empty(h, np.int64), np.empty(h)
    _sampson_kernel(terms, candidates, limit, np.empty((0, 0)), counts, costs)
    # the most inliers, then the lowest cost, then the earliest (the IMU's own first)
    top = 0
    for j in range(1, h):
        if counts[j] > counts[top] or (counts[j] == counts[top] and costs[j] < costs[top]):
            top = j
    best = np.empty((1, 3))
    best[0, 0], best[0, 1], best[0, 2] = candidates[top, 0], candidates[top, 1], candidates[top, 2]
    d2 = np.empty((1, n))
    _sampson_kernel(terms, best, limit, d2, counts, costs)
    inlier = np.empty(n, np.bool_)
    for i in range(n):
        inlier[i] = d2[0, i] < limit
    # refine the direction on the inliers (smallest singular vector of their normals)
    # (the smallest eigenvector of their scatter: the smallest right singular vector)
    scatter = np.zeros((3, 3))
    m = 0
    for i in range(n):
        if inlier[i]:
            w = 1.0 / (normals[i, 0] ** 2 + normals[i, 1] ** 2 + normals[i, 2] ** 2)
            for r in range(3):
                for c in range(3):
                    scatter[r, c] += w * normals[i, r] * normals[i, c]
            m += 1
    if m >= 3:
        v = np.linalg.eigh(scatter)[1]  # its first column
        sign = 1.0 if v[0, 0] * prior[0] + v[1, 0] * prior[1] + v[2, 0] * prior[2] >= 0 else -1.0
        best[0, 0], best[0, 1], best[0, 2] = sign * v[0, 0], sign * v[1, 0], sign * v[2, 0]
        _sampson_kernel(terms, best, limit, d2, counts, costs)
        for i in range(n):
            inlier[i] = d2[0, i] < limit
    return best[0], inlier


def check_pair(q_a: np.ndarray, q_b: np.ndarray, R_ba: np.ndarray, t_b: np.ndarray,
               sigma_q: float, range_m: float, settings: EpipolarSettings | None = None,
               ) -> EpipolarCheck:
    """Which features of a pair agree with the epipolar geometry.

    Args:
        q_a, q_b: (n, 3) normalized rays (z = 1) in cameras a and b.
        R_ba: (3, 3) rotation from camera a to camera b (``R_b^T R_a``).
        t_b: (3,) camera a's centre in camera b (``R_b^T (p_a - p_b)``), the prior.
        sigma_q: 1-sigma pixel noise of one observation in normalized units.
        range_m: typical distance to the ground, for the parallax test.
        settings: the check's settings.

    Returns:
        The inliers and the direction found.
    """
    settings = settings or EpipolarSettings()
    n = q_a.shape[0]
    baseline = float(np.linalg.norm(t_b))
    prior = t_b / baseline if baseline > 0 else np.array([0.0, 0.0, 1.0])
    # both observations are noisy: sqrt(2) sigma in the Sampson distance
    sigma = np.sqrt(2.0) * sigma_q
    if n < 3 or baseline / max(range_m, 1e-9) < settings.min_parallax_sigmas * sigma:
        return EpipolarCheck(np.ones(n, dtype=bool), prior, False, 0.0)
    limit = settings.gate * sigma * sigma
    c = np.ascontiguousarray
    best, inlier = _ransac(c(q_a, float), c(q_b, float), c(R_ba, float), c(prior, float),
                           _picks(settings.seed, n, settings.hypotheses), limit)
    angle = float(np.arccos(np.clip(best @ prior, -1.0, 1.0)))
    return EpipolarCheck(inlier, best, True, angle)
