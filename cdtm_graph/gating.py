"""Chi-square tests of C-DTM features: innovations against the prior, residuals at a solution.

The statistics a feature is judged by, in one place: the gate of the incremental smoother
(``innovation_mahalanobis`` against the prior covariance of its two poses) and the outlier
count at a solution (``count_outliers``).
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from factors import CdtmPairFactor


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
    """Features whose whitened residual fails the chi-square(2) 99.9% gate at given poses.

    The same gate whatever the robust kernel (the kernel decides the weighting; a
    Huber threshold of 1.345 would call 40% of Gaussian inliers outliers).

    Returns:
        The total and the count per frame (by the pair's later frame), (K,).
    """
    per_frame = np.zeros(n_frames, dtype=int)
    for f in factors:
        a = int(gtsam.Symbol(f.key_a).index())
        b = int(gtsam.Symbol(f.key_b).index())
        r2 = np.sum(f.whitened_residuals(world_T_body[a], world_T_body[b]) ** 2, axis=1)
        per_frame[b] += int(np.count_nonzero(r2 > CHI2_2DOF_999))
    return int(per_frame.sum()), per_frame


