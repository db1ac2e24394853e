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

from dataclasses import dataclass

import numpy as np

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


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` over the last axis (broadcast), without its per-call overhead (the
    check runs a few of them per pair: np.cross was half its time)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _sampson_sq(q_a: np.ndarray, q_b: np.ndarray, R_ba: np.ndarray,
                t_b: np.ndarray) -> np.ndarray:
    """Squared Sampson distances of ``q_b^T E q_a = 0``, E = [t]x R, normalized units:
    (n,) for one direction ``t_b`` (3,), (h, n) for h directions (h, 3) at once."""
    t = np.atleast_2d(t_b)[:, None, :]   # (h, 1, 3)
    Rq = q_a @ R_ba.T
    Eq_a = _cross(t, Rq)                # E q_a, (h, n, 3)
    Et_q_b = _cross(q_b, t) @ R_ba    # E^T q_b = R^T [t]x^T q_b = R^T (q_b x t)
    num = np.einsum("ni,hni->hn", q_b, Eq_a) ** 2
    den = Eq_a[..., 0] ** 2 + Eq_a[..., 1] ** 2 + Et_q_b[..., 0] ** 2 + Et_q_b[..., 1] ** 2
    d2 = num / np.maximum(den, 1e-300)
    return d2 if np.ndim(t_b) == 2 else d2[0]


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
    # each feature's epipolar plane normal; t must be perpendicular to every inlier's
    normals = _cross(q_b, q_a @ R_ba.T)
    rng = np.random.default_rng(settings.seed)
    picks = rng.integers(0, n, (settings.hypotheses, 2))
    candidates = _cross(normals[picks[:, 0]], normals[picks[:, 1]])
    norm = np.linalg.norm(candidates, axis=1)
    candidates = candidates[norm > 1e-12] / norm[norm > 1e-12, None]
    # the sign of t: the one closer to the IMU's (a direction and its opposite fit alike)
    candidates *= np.where(candidates @ prior < 0, -1.0, 1.0)[:, None]
    candidates = np.vstack([prior, candidates])
    d2 = _sampson_sq(q_a, q_b, R_ba, candidates)  # (h, n): every hypothesis at once
    counts = (d2 < limit).sum(axis=1)
    costs = np.minimum(d2, limit).sum(axis=1)  # MSAC: ties go to the tighter fit
    # the most inliers, then the lowest cost, then the earliest (the IMU's own first)
    best = candidates[np.lexsort((np.arange(len(counts)), costs, -counts))[0]]
    inlier = _sampson_sq(q_a, q_b, R_ba, best) < limit
    # refine the direction on the inliers (smallest singular vector of their normals)
    if inlier.sum() >= 3:
        _, _, vt = np.linalg.svd(normals[inlier] / np.linalg.norm(
            normals[inlier], axis=1, keepdims=True), full_matrices=False)
        refined = vt[-1] * (1.0 if vt[-1] @ prior >= 0 else -1.0)
        inlier = _sampson_sq(q_a, q_b, R_ba, refined) < limit
        best = refined
    angle = float(np.arccos(np.clip(best @ prior, -1.0, 1.0)))
    return EpipolarCheck(inlier, best, True, angle)
