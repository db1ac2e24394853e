"""Chi-square tests of features: the innovation distance and its quantiles."""

from __future__ import annotations

import numpy as np
import pytest

from cdtm_graph.robust.gating import (
    chi2_2dof_quantile,
    innovation_covariance,
    innovation_mahalanobis,
)


def test_innovation_distance_is_chi_square_2_for_a_linear_gaussian_model(rng):
    """e = H dx + v with dx ~ N(0, P), v ~ N(0, I): d is chi-square(2), and the gate of
    probability p passes a fraction p."""
    n = 20000
    L = rng.normal(size=(12, 12))
    P = L @ L.T * 0.01 + np.diag(rng.uniform(0.001, 0.1, 12))
    H_a, H_b = rng.normal(size=(n, 2, 6)), rng.normal(size=(n, 2, 6))
    dx = rng.multivariate_normal(np.zeros(12), P, n)
    e = np.einsum("nij,nj->ni", np.concatenate([H_a, H_b], axis=2), dx) + rng.normal(size=(n, 2))
    d = innovation_mahalanobis(e, H_a, H_b, P)
    assert abs(d.mean() - 2.0) < 4 * 2.0 / np.sqrt(n)  # chi2_2: mean 2, std 2
    for p in (0.9, 0.99):
        passed = np.mean(d <= chi2_2dof_quantile(p))
        assert abs(passed - p) < 4 * np.sqrt(p * (1 - p) / n)
    with pytest.raises(ValueError):
        chi2_2dof_quantile(1.0)


def test_innovation_distance_is_e_S_inverse_e_with_a_measurement_covariance(rng):
    """Against the formula as written: S = R + H P H^T (H = [H_a H_b]), d = e^T S^-1 e."""
    n = 50
    L = rng.normal(size=(12, 12))
    P = L @ L.T * 0.01
    H_a, H_b = rng.normal(size=(n, 2, 6)), rng.normal(size=(n, 2, 6))
    M = rng.normal(size=(n, 2, 2))
    R = M @ np.swapaxes(M, 1, 2) + 0.1 * np.eye(2)
    e = rng.normal(size=(n, 2))
    H = np.concatenate([H_a, H_b], axis=2)
    S = R + H @ P @ np.swapaxes(H, 1, 2)
    expected = [e[i] @ np.linalg.solve(S[i], e[i]) for i in range(n)]
    np.testing.assert_allclose(innovation_covariance(H_a, H_b, P, R), S, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(innovation_covariance(H_a, H_b, P), S - R + np.eye(2),
                               rtol=1e-12, atol=1e-12)
    one_R = R[0]  # one measurement covariance for all
    np.testing.assert_allclose(innovation_covariance(H_a, H_b, P, one_R), S - R + one_R,
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(innovation_mahalanobis(e, H_a, H_b, P, R), expected, rtol=1e-10)


def test_the_gates_median_is_numpys(rng):
    """The over-dispersion's median (one partition; the map error's solve uses it too)
    equals ``np.median``: odd and even sizes, one element, and NaN when one distance is
    NaN."""
    from cdtm_graph.constants import median as _median

    for n in (1, 2, 3, 170, 171, 1000, 1001):
        for _ in range(50):
            d = rng.chisquare(2, n)
            assert _median(d) == np.median(d)
    d = rng.chisquare(2, 20)
    d[5] = np.nan
    assert np.isnan(_median(d))
