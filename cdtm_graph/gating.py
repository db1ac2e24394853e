"""Chi-square tests of C-DTM features: innovations against the prior, residuals at a solution.

The statistics a feature is judged by, in one place: the gate of the incremental smoother
(``innovation_mahalanobis`` against the prior covariance of its two poses) and the outlier
count at a solution (``count_outliers``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import gtsam
import numpy as np

from cdtm_graph.results import Rejection, Rejections
from factors import CdtmPairFactor, FeatureNoise


def chi2_2dof_quantile(p: float) -> float:
    """The p-quantile of chi-square with 2 degrees of freedom: ``-2 ln(1 - p)``."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"gate probability {p}: expected 0 < p < 1")
    return float(-2.0 * np.log1p(-p))


def innovation_mahalanobis(e: np.ndarray, H_a: np.ndarray, H_b: np.ndarray, P: np.ndarray,
                           R: np.ndarray | None = None) -> np.ndarray:
    """Squared Mahalanobis distance of each feature's innovation, (n,).

    ``d_i = e_i^T S_i^-1 e_i`` with ``S_i = R_i + H_i P H_i^T``: ``e`` (n, 2) are the
    whitened residuals, ``R`` (n, 2, 2) their measurement covariance in the same whitened
    coordinates (the identity if ``None``) and ``H_i = [H_a,i H_b,i]`` (n, 2, 12) maps the
    joint tangent of ``(X(a), X(b))``, whose prior covariance is ``P`` (12, 12), into the
    residual. Chi-square with 2 degrees of freedom for an inlier whose prior is honest.
    """
    H = np.concatenate([H_a, H_b], axis=2)
    S = H @ P @ np.swapaxes(H, 1, 2) + (np.eye(2) if R is None else R)
    return np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0])


#: Inlier gate without a robust kernel: chi-square with 2 dof, 99.9%.
CHI2_2DOF_999 = chi2_2dof_quantile(0.999)


def count_outliers(factors: Sequence[CdtmPairFactor],
                   world_T_body: Sequence[np.ndarray] | np.ndarray,
                   n_frames: int) -> tuple[int, np.ndarray]:
    """Features whose residual fails the chi-square(2) 99.9% test at given poses.

    The residual is judged as measured (both observations' pixel noise and the DTM's:
    ``CdtmPairFactor.normalized_residuals``), so a clean log has ~0.1% beyond the test;
    with the factor's own whitening, which leaves the first observation's pixel noise to
    the previous pair, 2.5% of clean features failed it. The same test whatever the
    robust kernel (the kernel decides the weighting).

    Returns:
        The total and the count per frame (by the pair's later frame), (K,).
    """
    per_frame = np.zeros(n_frames, dtype=int)
    for f in factors:
        a = int(gtsam.Symbol(f.key_a).index())
        b = int(gtsam.Symbol(f.key_b).index())
        d = f.normalized_residuals(world_T_body[a], world_T_body[b])
        per_frame[b] += int(np.count_nonzero(d > CHI2_2DOF_999))
    return int(per_frame.sum()), per_frame


class InnovationGate:
    """Drops each new feature whose innovation fails a chi-square(2) gate against the prior.

    The prior is the joint covariance of the feature's two poses after the frame's IMU
    factor (before its C-DTM factors), from the incremental solver. The factors leave the
    first observation's pixel noise out (each observation is the second of one pair and
    the first of the next); a fresh innovation has it, so the gate counts it (without it
    the innovations were 1.8x over-dispersed: docs/design.md).

    Args:
        probability: gate probability, e.g. 0.999.
        noise: the factors' data noise.
        dtm_spacing_m: the DTM's grid spacing. Where the newer pose is uncertain by more
            than a cell (the first frame under its initial prior), the tangent-plane
            linearization cannot judge a feature: such pairs pass untested.

        rejections: where the dropped features are counted (``Rejection.GATED``).

    Attributes:
        nis: squared Mahalanobis distance of every innovation tested, per call.
    """

    def __init__(self, probability: float, noise: FeatureNoise, dtm_spacing_m: float,
                 rejections: Rejections):
        self.threshold = chi2_2dof_quantile(probability)
        self._noise = replace(noise, sigma_qa_xy=noise.sigma_q_xy)
        self._spacing_m = float(dtm_spacing_m)
        self._rejections = rejections
        self.nis: list[np.ndarray] = []

    def apply(self, k: int, factors: Sequence[CdtmPairFactor],
              pose: Callable[[int], np.ndarray],
              joint_covariance: Callable[[int, int], np.ndarray]) -> list[CdtmPairFactor]:
        """The factors of frame k with only the features that pass.

        Args:
            k: the newest frame (every factor's later pose).
            factors: its new C-DTM factors.
            pose: frame -> current (4, 4) ``world_T_body`` estimate.
            joint_covariance: (key_a, key_b) -> (12, 12) prior covariance of the two poses.
        """
        kept: list[CdtmPairFactor] = []
        n_gated = 0
        pose_k = pose(k)
        for f in factors:
            P = joint_covariance(f.key_a, f.key_b)
            if np.sqrt(np.linalg.eigvalsh(P[9:, 9:]).max()) > self._spacing_m:
                kept.append(f)  # the DTM plane at the guess means nothing a cell away
                continue
            pose_a = pose(int(gtsam.Symbol(f.key_a).index()))
            e, H_a, H_b = f.innovations(pose_a, pose_k)
            R = f.whitened_noise(pose_a, pose_k, self._noise)
            d = innovation_mahalanobis(e, H_a, H_b, P, R)
            self.nis.append(d)
            passed = d <= self.threshold
            n_gated += int(f.features.n - passed.sum())
            if passed.all():
                kept.append(f)
            elif passed.any():
                kept.append(f.with_features(passed))
        self._rejections.add(Rejection.GATED, k, n_gated)
        return kept

    @property
    def all_nis(self) -> np.ndarray:
        """Every distance tested, (n,): chi-square(2) (median 1.39, mean 2) when the noise
        model and the prior are honest."""
        return np.concatenate(self.nis) if self.nis else np.zeros(0)
