"""Chi-square tests of C-DTM features: innovations against the prior, residuals at a solution.

The statistics a feature is judged by, in one place: the gate of the incremental smoother
(``innovation_mahalanobis`` against the prior covariance of its two poses) and the outlier
count and residual chi-square at a solution (``residual_test``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from cdtm_graph.constants import chi2_2dof_quantile, median
from cdtm_graph.geometry import largest_eigenvalue_sym3
from cdtm_graph.results import Rejection, Rejections
from factors import CdtmPairFactor
from factors.jit import njit


def innovation_mahalanobis(e: np.ndarray, H_a: np.ndarray, H_b: np.ndarray, P: np.ndarray,
                           R: np.ndarray | None = None) -> np.ndarray:
    """Squared Mahalanobis distance of each feature's innovation, (n,).

    ``d_i = e_i^T S_i^-1 e_i`` with ``S_i = R_i + H_i P H_i^T``: ``e`` (n, 2) are the
    whitened residuals, ``R`` (n, 2, 2) their measurement covariance in the same whitened
    coordinates (the identity if ``None``) and ``H_i = [H_a,i H_b,i]`` (n, 2, 12) maps the
    joint tangent of ``(X(a), X(b))``, whose prior covariance is ``P`` (12, 12), into the
    residual. Chi-square with 2 degrees of freedom for an inlier whose prior is honest.
    """
    return mahalanobis_2d(e, innovation_covariance(H_a, H_b, P, R))


def innovation_covariance(H_a: np.ndarray, H_b: np.ndarray, P: np.ndarray,
                          R: np.ndarray | None = None) -> np.ndarray:
    """Each feature's innovation covariance ``S_i = R_i + H_i P H_i^T``, (n, 2, 2)
    (:func:`innovation_mahalanobis`)."""
    n = H_a.shape[0]
    R = np.broadcast_to(np.eye(2) if R is None else R, (n, 2, 2))
    # compiled: a frame's few hundred 2x12 products are too small for numpy's calls
    return _innovation_covariance(np.ascontiguousarray(H_a, float),
                                  np.ascontiguousarray(H_b, float),
                                  np.ascontiguousarray(P, float), np.ascontiguousarray(R, float))


@njit(cache=True)
def _innovation_covariance(H_a, H_b, P, R):
    n = H_a.shape[0]
    S = np.empty((n, 2, 2))
    H, HP = np.empty((2, 12)), np.empty((2, 12))
    for i in range(n):
        for r in range(2):
            for j in range(6):
                H[r, j], H[r, 6 + j] = H_a[i, r, j], H_b[i, r, j]
        for r in range(2):
            for c in range(12):
                total = 0.0
                for j in range(12):
                    total += H[r, j] * P[j, c]
                HP[r, c] = total
        for r in range(2):
            for c in range(2):
                total = 0.0
                for j in range(12):
                    total += HP[r, j] * H[c, j]
                S[i, r, c] = total + R[i, r, c]
    return S


def mahalanobis_2d(e: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``e_i^T S_i^-1 e_i`` for (n, 2) ``e`` and symmetric (n, 2, 2) ``S`` (the inverse
    written out: numpy's stacked 2x2 solve costs more than the rest of a gate)."""
    s00, s01, s11 = S[:, 0, 0], 0.5 * (S[:, 0, 1] + S[:, 1, 0]), S[:, 1, 1]
    e0, e1 = e[:, 0], e[:, 1]
    return (s11 * e0 * e0 - 2.0 * s01 * e0 * e1 + s00 * e1 * e1) / (s00 * s11 - s01 * s01)


#: Probability of the outlier test at a solution (:func:`residual_test`).
OUTLIER_TEST_PROBABILITY = 0.999
#: Inlier gate without a robust kernel: chi-square with 2 dof, 99.9%.
CHI2_2DOF_999 = chi2_2dof_quantile(OUTLIER_TEST_PROBABILITY)
CHI2_2DOF_MEDIAN = chi2_2dof_quantile(0.5)  # 2 ln 2


def truncated_chi2_2dof_mean(probability: float) -> float:
    """Mean of chi-square(2) truncated at its ``probability`` quantile ``c``:
    ``2 - c (1 - p) / p`` (1.986 at 0.999), the expected residual of a feature within the
    test of :func:`residual_test`."""
    c = chi2_2dof_quantile(probability)
    return 2.0 - c * (1.0 - probability) / probability


@dataclass(frozen=True)
class ResidualTest:
    """The C-DTM features judged at a solution, by the frame their pair ends at.

    Attributes:
        outliers_per_frame: (K,) features beyond the chi-square(2) 99.9% test.
        chi2_within_per_frame: (K,) sum of the squared Mahalanobis distances of the
            features within the test (``CdtmPairFactor.normalized_residuals``): the
            residual chi-square a self-check compares with its expectation.
    """

    outliers_per_frame: np.ndarray
    chi2_within_per_frame: np.ndarray

    @property
    def n_outliers(self) -> int:
        return int(self.outliers_per_frame.sum())


def residual_test(factors: Sequence[CdtmPairFactor],
                  world_T_body: Sequence[np.ndarray] | np.ndarray,
                  n_frames: int) -> ResidualTest:
    """Each feature's residual at given poses against the chi-square(2) 99.9% test.

    The residual is judged as measured (both observations' pixel noise and the DTM's:
    ``CdtmPairFactor.normalized_residuals``), so a clean log has ~0.1% beyond the test;
    with the factor's own whitening, which leaves the first observation's pixel noise to
    the previous pair, 2.5% of clean features failed it. The same test whatever the
    robust kernel (the kernel decides the weighting).
    """
    outliers = np.zeros(n_frames, dtype=int)
    chi2_within = np.zeros(n_frames)
    for f in factors:
        a = int(gtsam.Symbol(f.key_a).index())
        b = int(gtsam.Symbol(f.key_b).index())
        d = f.normalized_residuals(world_T_body[a], world_T_body[b])
        beyond = d > CHI2_2DOF_999
        outliers[b] += int(np.count_nonzero(beyond))
        chi2_within[b] += float(d[~beyond].sum())
    return ResidualTest(outliers, chi2_within)


def count_outliers(factors: Sequence[CdtmPairFactor],
                   world_T_body: Sequence[np.ndarray] | np.ndarray,
                   n_frames: int) -> tuple[int, np.ndarray]:
    """Features whose residual fails the chi-square(2) 99.9% test at given poses
    (:func:`residual_test`): the total and the count per frame (by the pair's later
    frame), (K,)."""
    test = residual_test(factors, world_T_body, n_frames)
    return test.n_outliers, test.outliers_per_frame


class InnovationGate:
    """Each new feature's innovation against the prior covariance of its two poses.

    The prior is the joint covariance of the pair's poses before the frame's C-DTM
    factors (the IMU's prediction of the new pose, :func:`cdtm_graph.imu.
    propagate_covariance`). Two uses:

    * the robust kernel's scale: each feature's residual is judged against its
      innovation's spread, ``sqrt(trace(S) / 2)`` with ``S = R + H P H^T``, not the bare
      measurement noise. While the poses are uncertain (the first frames under a loose
      prior) the redescending kernel is then nearly quadratic and pulls the solution in;
      as they settle, it tightens to the measurement noise. The kernel is reached
      without its local-minimum trap (graduated by the prior, not by a schedule).
    * with a ``probability``, the chi-square(2) gate: a feature whose squared Mahalanobis
      distance ``e^T S^-1 e`` fails it is dropped before it enters (counted). The
      distances are first divided by the frame's robust over-dispersion (their median
      over chi-square(2)'s, when above 1, with enough features): while the solution
      still settles, the prior is too tight for every feature alike, which is not what
      an outlier looks like (half of a frame's features would have to be outliers to
      move the median).

    ``R`` includes the first observation's pixel noise, which the factors leave to the
    previous pair: a fresh innovation carries it (without it the innovations were 1.8x
    over-dispersed; docs/design.md).

    Args:
        probability: gate probability, e.g. 0.999; ``None`` tests nothing.
        dtm_spacing_m: the DTM's grid spacing. Where the newer pose is uncertain by more
            than a cell (the first frame under its initial prior), the tangent-plane
            linearization cannot judge a feature: such pairs are not tested.
        rejections: where the dropped features are counted (``Rejection.GATED``).

    Attributes:
        nis: squared Mahalanobis distance of every innovation tested, per call (as
            measured, before the over-dispersion is divided out).
    """

    def __init__(self, probability: float | None, dtm_spacing_m: float,
                 rejections: Rejections):
        self.threshold = None if probability is None else chi2_2dof_quantile(probability)
        self._spacing_m = float(dtm_spacing_m)
        self._rejections = rejections
        self.nis: list[np.ndarray] = []

    def apply(self, k: int, factors: Sequence[CdtmPairFactor], track_ids: Sequence[np.ndarray],
              pose: Callable[[int], np.ndarray], prior: Callable[[int], np.ndarray],
              test: bool = True) -> tuple[list[CdtmPairFactor], list[np.ndarray]]:
        """Frame k's factors with their kernels scaled, and only the features that pass.

        Args:
            k: the newest frame (every factor's later pose).
            factors: its new C-DTM factors; track_ids: their features' track ids.
            pose: frame -> current (4, 4) ``world_T_body`` guess.
            prior: earlier frame a -> (12, 12) prior covariance of ``(X(a), X(k))``.
            test: False while the solution still warms up from a loose prior: scale, do
                not drop.

        Returns:
            The factors and their features' track ids.
        """
        scaled: list[CdtmPairFactor] = []
        distances: list[np.ndarray] = []
        judged: list[bool] = []
        pose_k = pose(k)
        for f in factors:
            a = int(gtsam.Symbol(f.key_a).index())
            P = prior(a)
            e, H_a, H_b = f.innovations(pose(a), pose_k)
            S = innovation_covariance(H_a, H_b, P, f.features.whitened_full_covariance())
            scaled.append(f.with_robust_scale(np.sqrt(0.5 * (S[:, 0, 0] + S[:, 1, 1]))))
            distances.append(mahalanobis_2d(e, S))
            # the DTM plane at the guess means nothing a cell away: no judging there
            judged.append(test and self.threshold is not None
                          and _sigmas_within(P[9:, 9:], self._spacing_m))
        tested = [d for d, j in zip(distances, judged) if j]
        if not tested:
            return scaled, list(track_ids)
        d_all = np.concatenate(tested)
        self.nis.append(d_all)
        spread = (max(1.0, median(d_all) / CHI2_2DOF_MEDIAN)
                  if d_all.size >= self.MIN_FOR_SPREAD else 1.0)
        kept: list[CdtmPairFactor] = []
        kept_ids: list[np.ndarray] = []
        n_gated = 0
        for f, ids, d, j in zip(scaled, track_ids, distances, judged):
            passed = (d / spread <= self.threshold if j and self.threshold is not None
                      else np.ones(d.size, dtype=bool))
            n_gated += int((~passed).sum())
            if passed.all():
                kept.append(f)
                kept_ids.append(ids)
            elif passed.any():
                kept.append(f.with_features(passed))
                kept_ids.append(ids[passed])
        self._rejections.add(Rejection.GATED, k, n_gated)
        return kept, kept_ids

    #: Fewer tested features than this: their median says too little to rescale by.
    MIN_FOR_SPREAD = 20

    @property
    def all_nis(self) -> np.ndarray:
        """Every distance tested, (n,): chi-square(2) (median 1.39, mean 2) when the noise
        model and the prior are honest."""
        return np.concatenate(self.nis) if self.nis else np.zeros(0)


def _sigmas_within(cov: np.ndarray, limit: float) -> bool:
    """Whether every 1-sigma of a 3x3 covariance is within ``limit``: its largest eigenvalue
    against ``limit^2``, settled by the trace (an upper bound) where it can be."""
    return bool(np.trace(cov) <= limit * limit
                or largest_eigenvalue_sym3(cov) <= limit * limit)
