"""The C-DTM factor: Jacobians against central differences, both forms agree."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from cdtm_graph.geometry import make_pose
from factors import (
    CdtmPairFactor,
    FeatureNoise,
    PairFeatures,
    PlaneMode,
    RobustKernel,
    cdtm_math,
    make_feature_factors,
)
from factors.kernel import _gram_triangle, _householder_triangle, triangularize

#: Random configurations per test: a wrong derivative shows on every one (30, as the
#: calibration's Jacobian test: 100 took 6 s of the suite's CPU for nothing more).
N_CONFIGURATIONS = 30
#: Central differences with a 1e-6 step agree with exact derivatives to ~1e-9 relative.
JACOBIAN_RTOL = 1e-6
#: Two forms of one linear system, accumulated in different orders.
LINEARIZATION_RTOL = 1e-9
#: Monte Carlo of the innovation spread: 4000 draws give ~2% relative error (4 sigma: 0.1).
N_PRIOR_DRAWS = 4000
SPREAD_TOL = 0.1


@pytest.mark.parametrize("mode", [PlaneMode.FIXED, PlaneMode.REINTERSECT])
def test_pose_jacobians_match_central_differences(manifold, rng, mode):
    worst = 0.0
    for _ in range(N_CONFIGURATIONS):
        terrain = manifold.WavyTerrain(
            amplitude_m=rng.uniform(10, 60), wavelength_m=rng.uniform(300, 900)
        )
        body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain)
        fac = CdtmPairFactor(X(0), X(1), feats, body_T_cam, mode, raycast=terrain.raycast)
        _, Ha, Hb = (a.copy() for a in fac.evaluate(Ta, Tb))
        num_a = manifold.numerical_pose_jacobian(
            lambda T: fac.evaluate(T, Tb)[0].ravel().copy(), Ta
        )
        num_b = manifold.numerical_pose_jacobian(
            lambda T: fac.evaluate(Ta, T)[0].ravel().copy(), Tb
        )
        scale = max(np.abs(num_a).max(), np.abs(num_b).max())
        err = max(np.abs(Ha.reshape(-1, 6) - num_a).max(), np.abs(Hb.reshape(-1, 6) - num_b).max())
        worst = max(worst, err / scale)
    assert worst < JACOBIAN_RTOL


def test_reintersect_uses_the_plane_at_the_new_hit(manifold, rng):
    """Away from the construction pose, REINTERSECT equals a FIXED factor built on the new hits."""
    terrain = manifold.WavyTerrain(amplitude_m=60.0, wavelength_m=400.0)
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain)
    moved = Ta @ make_pose(np.eye(3), [30.0, -20.0, 5.0])
    wTc_moved = moved @ body_T_cam
    ray = feats.q_a @ wTc_moved[:3, :3].T
    G_new, N_new, _ = terrain.raycast(np.broadcast_to(wTc_moved[:3, 3], ray.shape), ray)
    refit = PairFeatures(feats.q_a, feats.q_b, G_new, N_new, feats.Sigma_e, feats.Sigma_f,
                         feats.basis_b, feats.sqrt_info)
    fixed = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.FIXED)
    fixed_new = CdtmPairFactor(X(0), X(1), refit, body_T_cam, PlaneMode.FIXED)
    reint = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.REINTERSECT, terrain.raycast)
    e_reint = reint.evaluate(moved, Tb)[0].copy()
    np.testing.assert_allclose(e_reint, fixed_new.evaluate(moved, Tb)[0], atol=1e-12)
    assert np.abs(e_reint - fixed.evaluate(moved, Tb)[0]).max() > 0.1  # whitened units
    np.testing.assert_allclose(fixed.evaluate(Ta, Tb)[0], reint.evaluate(Ta, Tb)[0], atol=1e-9)


def test_a_derived_factor_keeps_the_planes_cast_at_the_same_pose(manifold, rng):
    """``with_features``, ``with_robust_scale`` and ``refreshed`` hand on the planes the
    factor cast last: evaluated at that pose, the derived factor casts nothing and equals
    one that cast its own; at another pose it casts anew."""
    terrain = manifold.WavyTerrain(amplitude_m=60.0, wavelength_m=400.0)
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain)
    casts = []

    def raycast(origin, ray):
        casts.append(len(ray))
        return terrain.raycast(np.broadcast_to(origin, ray.shape), ray)

    moved = Ta @ make_pose(np.eye(3), [30.0, -20.0, 5.0])
    reint = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.REINTERSECT, raycast)
    reint.evaluate(moved, Tb)
    keep = np.arange(feats.n) % 3 != 0
    derived = reint.with_features(keep).with_robust_scale(np.full(keep.sum(), 2.0))
    n_casts = len(casts)
    e_derived = derived.evaluate(moved, Tb)[0].copy()
    assert len(casts) == n_casts
    own = CdtmPairFactor(X(0), X(1), feats.subset(keep), body_T_cam, PlaneMode.REINTERSECT,
                         raycast).with_robust_scale(np.full(keep.sum(), 2.0))
    np.testing.assert_array_equal(e_derived, own.evaluate(moved, Tb)[0])
    refreshed = reint.refreshed(moved, Tb)
    n_casts = len(casts)
    refreshed.evaluate(moved, Tb)
    assert len(casts) == n_casts
    derived.evaluate(Ta, Tb)
    assert len(casts) == n_casts + 1


@pytest.mark.parametrize("robust", [RobustKernel.NONE, RobustKernel.CAUCHY])
def test_an_error_then_a_linearization_at_the_same_poses_are_what_each_gives_alone(manifold, rng,
                                                                                   robust):
    """The factor keeps what it made at the last poses (the Jacobians too, at an error
    evaluation): the next call there, with or without Jacobians, and calls at other poses
    give what a fresh factor gives."""
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, n=40, pixel_noise=8e-3)
    moved = Ta @ make_pose(np.eye(3), [3.0, -2.0, 1.0])

    def fresh(Tx, want):
        f = CdtmPairFactor(X(0), X(1), feats, body_T_cam, robust=robust)
        return [a.copy() for a in f.evaluate(Tx, Tb, want)]

    factor = CdtmPairFactor(X(0), X(1), feats, body_T_cam, robust=robust)
    for Tx, want in ((moved, False), (moved, True), (moved, False), (Ta, True), (Ta, False),
                     (moved, True)):
        got = factor.evaluate(Tx, Tb, want)
        expected = fresh(Tx, want)
        np.testing.assert_array_equal(got[0], expected[0])
        if want:
            np.testing.assert_array_equal(got[1], expected[1])
            np.testing.assert_array_equal(got[2], expected[2])
    if robust is not RobustKernel.NONE:  # the two residuals differ under a kernel
        assert np.abs(fresh(moved, True)[0] - fresh(moved, False)[0]).max() > 1e-3


def test_data_jacobians_match_central_differences(manifold, rng):
    """Eq. 19 (q_b), eq. 20 (G_E) and the q_a Jacobian, feature by feature."""
    worst = 0.0
    for _ in range(N_CONFIGURATIONS):
        body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, n=3, pixel_noise=5e-3)
        wTc_a, wTc_b = Ta @ body_T_cam, Tb @ body_T_cam
        args = (wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3])
        J_qb, J_G, J_qa = cdtm_math.paper_data_jacobians(
            *args, feats.q_a, feats.q_b, feats.G_E, feats.N)
        for i in range(feats.n):
            one = slice(i, i + 1)
            qa, qb, G, N = feats.q_a[one], feats.q_b[one], feats.G_E[one], feats.N[one]

            def f_of(qa=qa, qb=qb, G=G, N=N):
                return cdtm_math.paper_residual(*args, qa, qb, G, N)[0][0]

            checks = [
                (J_qb[i], manifold.numerical_jacobian(lambda x: f_of(qb=x[None]), qb[0])),
                (J_G[i], manifold.numerical_jacobian(lambda x: f_of(G=x[None]), G[0], step=1e-4)),
                (J_qa[i], manifold.numerical_jacobian(lambda x: f_of(qa=x[None]), qa[0])),
            ]
            for analytic, numeric in checks:
                worst = max(worst, np.abs(analytic - numeric).max() / np.abs(numeric).max())
    assert worst < JACOBIAN_RTOL


def test_factor_residual_is_paper_residual_in_the_basis(manifold, rng):
    """e = B^T f: the factor's 2-vector carries the paper's eq. 7 residual."""
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, pixel_noise=5e-3)
    wTc_a, wTc_b = Ta @ body_T_cam, Tb @ body_T_cam
    f, _ = cdtm_math.paper_residual(wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3],
                                    feats.q_a, feats.q_b, feats.G_E, feats.N)
    unwhitened = PairFeatures(feats.q_a, feats.q_b, feats.G_E, feats.N, feats.Sigma_e,
                              feats.Sigma_f,
                              feats.basis_b, np.repeat(np.eye(2)[None], feats.n, 0))
    e = CdtmPairFactor(X(0), X(1), unwhitened, body_T_cam).evaluate(Ta, Tb)[0]
    np.testing.assert_allclose(e, np.einsum("nik,ni->nk", feats.basis_b, f), atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), np.linalg.norm(f, axis=1), rtol=1e-12)


def _linear_system(factors, Ta, Tb):
    graph = gtsam.NonlinearFactorGraph()
    for f in factors:
        graph.add(f)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(Ta))
    values.insert(X(1), gtsam.Pose3(Tb))
    return graph.linearize(values).augmentedHessian(), graph.error(values)


@pytest.mark.parametrize("robust", list(RobustKernel))
@pytest.mark.parametrize("mode", [PlaneMode.FIXED, PlaneMode.REINTERSECT])
def test_batched_and_per_feature_factors_linearize_identically(manifold, rng, robust, mode):
    terrain = manifold.WavyTerrain()
    for _ in range(5):
        # Large pixel noise so that many features sit beyond the robust thresholds.
        body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain, n=40, pixel_noise=8e-3)
        moved = Ta @ make_pose(np.eye(3), [3.0, -2.0, 1.0])  # off the construction pose
        batched = CdtmPairFactor(X(0), X(1), feats, body_T_cam, mode, terrain.raycast, robust)
        single = make_feature_factors(X(0), X(1), feats, body_T_cam, mode, terrain.raycast, robust)
        H_batched, err_batched = _linear_system([batched.factor], moved, Tb)
        H_single, err_single = _linear_system(single, moved, Tb)
        np.testing.assert_allclose(H_batched, H_single, rtol=LINEARIZATION_RTOL,
                                   atol=LINEARIZATION_RTOL * np.abs(H_single).max())
        np.testing.assert_allclose(err_batched, err_single, rtol=LINEARIZATION_RTOL)
        if robust is not RobustKernel.NONE:  # the comparison must involve down-weighted rows
            e_plain = CdtmPairFactor(X(0), X(1), feats, body_T_cam, mode,
                                     terrain.raycast).evaluate(moved, Tb)[0]
            assert np.any(np.linalg.norm(e_plain, axis=1) > robust.default_threshold)


@pytest.mark.parametrize("n", [3, 6, 7, 40])
def test_pair_factor_rows_are_the_triangle_of_its_features(manifold, rng, n):
    """More than six features reach GTSAM as 13 rows, with the raw rows' linear system.

    The linearized factor equals the one built from the 2n raw rows, constant term
    included (``|z| = |e|``), and an error evaluation still gives ``|e|^2 / 2``.
    """
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, n=n, pixel_noise=5e-3)
    moved = Ta @ make_pose(manifold.random_rotation(rng, 0.002), [2.0, -1.0, 0.5])
    factor = CdtmPairFactor(X(0), X(1), feats, body_T_cam)
    e, Ha, Hb = (a.copy() for a in factor.evaluate(moved, Tb))
    raw = gtsam.JacobianFactor(X(0), Ha.reshape(-1, 6), X(1), Hb.reshape(-1, 6), -e.reshape(-1),
                               gtsam.noiseModel.Unit.Create(2 * n))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(moved))
    values.insert(X(1), gtsam.Pose3(Tb))
    linear = factor.factor.linearize(values)
    assert linear.rows() == (2 * n if n <= 6 else 13)
    H = linear.augmentedInformation()
    np.testing.assert_allclose(H, raw.augmentedInformation(), rtol=1e-10,
                               atol=1e-12 * np.abs(H).max())
    np.testing.assert_allclose(factor.factor.error(values), 0.5 * np.sum(e * e), rtol=1e-12)


def _triangle(method, e, Ha, Hb):
    Ja, Jb, z = np.empty((13, 6)), np.empty((13, 6)), np.empty(13)
    if method is _gram_triangle:  # needs no scratch
        ok = method(e, Ha, Hb, Ja, Jb, z)
    else:  # scratch for the stacked rows' columns
        ok = method(e, Ha, Hb, np.empty((13, max(13, 2 * e.shape[0]))), Ja, Jb, z)
    return ok, np.c_[Ja, Jb, z]


def test_triangularize_handles_rank_deficient_rows(rng):
    """Zero and repeated columns (no information on a direction, as over flat ground)
    make the Cholesky path give up, and Householder's triangle has the same Gram matrix."""
    n = 20
    Ha, Hb = rng.normal(size=(n, 2, 6)), rng.normal(size=(n, 2, 6))
    Ha[:, :, 2] = 0.0
    Hb[:, :, 4] = Ha[:, :, 0]
    Hb[:, :, 5] = 0.0
    e = rng.normal(size=(n, 2))
    assert not _triangle(_gram_triangle, e, Ha, Hb)[0]
    _, T = _triangle(triangularize, e, Ha, Hb)
    A = np.c_[Ha.reshape(-1, 6), Hb.reshape(-1, 6), e.reshape(-1)]
    assert np.all(np.tril(T, -1) == 0.0)
    np.testing.assert_allclose(T.T @ T, A.T @ A, atol=1e-12 * np.abs(A.T @ A).max())


def test_cholesky_and_householder_triangles_agree(rng):
    """On well-posed rows (columns scaled 1e3 apart, as rotation vs translation) the fast
    Cholesky path is taken and gives Householder's triangle up to row signs."""
    n = 170
    Ha, Hb = rng.normal(size=(n, 2, 6)), rng.normal(size=(n, 2, 6))
    Ha[:, :, :3] *= 1e3
    e = rng.normal(size=(n, 2))
    ok, T_chol = _triangle(_gram_triangle, e, Ha, Hb)
    assert ok
    _, T_qr = _triangle(_householder_triangle, e, Ha, Hb)
    np.testing.assert_allclose(np.abs(T_chol), np.abs(T_qr), rtol=1e-9,
                               atol=1e-12 * np.abs(T_qr).max())


def test_robust_kernel_downweights_outliers(manifold, rng):
    """An outlier's rows shrink under Huber and vanish under Tukey beyond the threshold."""
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, n=10, pixel_noise=0.0)
    q_b = feats.q_b.copy()
    q_b[0, :2] += 0.05  # ~25 sigma
    feats = PairFeatures.build(Ta @ body_T_cam, Tb @ body_T_cam, feats.q_a, q_b, feats.G_E,
                               feats.N, manifold.PAIR_NOISE)
    plain = CdtmPairFactor(X(0), X(1), feats, body_T_cam).evaluate(Ta, Tb)[0].copy()
    huber = CdtmPairFactor(X(0), X(1), feats, body_T_cam, robust=RobustKernel.HUBER)
    tukey = CdtmPairFactor(X(0), X(1), feats, body_T_cam, robust=RobustKernel.TUKEY)
    s = np.linalg.norm(plain[0])
    k = RobustKernel.HUBER.default_threshold
    np.testing.assert_allclose(np.linalg.norm(huber.evaluate(Ta, Tb)[0][0]), np.sqrt(k / s) * s)
    assert np.all(tukey.evaluate(Ta, Tb)[0][0] == 0.0)
    np.testing.assert_allclose(huber.evaluate(Ta, Tb)[0][1:], plain[1:])


def test_noise_model_is_the_projected_feature_covariance(manifold, rng):
    """Sigma_e = B^T Sigma_f B and the whitening inverts it (eqs. 19-26)."""
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, pixel_noise=0.0)
    wTc_a, wTc_b = Ta @ body_T_cam, Tb @ body_T_cam
    args = (wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3], feats.q_a, feats.q_b,
            feats.G_E, feats.N)
    Sigma_f = cdtm_math.feature_covariance(
        *args,
        manifold.PAIR_NOISE.sigma_q_xy,
        manifold.PAIR_NOISE.sigma_h_m,
        manifold.PAIR_NOISE.sigma_qa_xy,
    )
    # At a noiseless solution Sigma_f has rank 2 with q_b in its null space.
    np.testing.assert_allclose(np.einsum("nij,nj->ni", Sigma_f, feats.q_b), 0, atol=1e-15)
    B = feats.basis_b
    np.testing.assert_allclose(np.swapaxes(B, 1, 2) @ Sigma_f @ B, feats.Sigma_e, rtol=1e-12)
    S = feats.sqrt_info
    np.testing.assert_allclose(S @ feats.Sigma_e @ np.swapaxes(S, 1, 2),
                               np.broadcast_to(np.eye(2), feats.Sigma_e.shape), atol=1e-9)


def test_numba_feature_covariance_equals_the_paper_formulas(manifold, rng):
    """PairFeatures.build's numba noise equals cdtm_math's formulas: Sigma_f (eqs. 19-26),
    the basis, Sigma_e and its whitening."""
    for qa_noise in (manifold.PAIR_NOISE.sigma_qa_xy, None):
        noise = FeatureNoise(
            manifold.PAIR_NOISE.sigma_q_xy, manifold.PAIR_NOISE.sigma_h_m, qa_noise
        )
        for _ in range(20):
            body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, pixel_noise=5e-3)
            wTc_a, wTc_b = Ta @ body_T_cam, Tb @ body_T_cam
            scale = rng.integers(1, 6, feats.n)  # pairs sharing each feature's DTM error
            built = PairFeatures.build(wTc_a, wTc_b, feats.q_a, feats.q_b, feats.G_E, feats.N,
                                       noise, scale)
            reference = cdtm_math.feature_covariance(
                wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3], feats.q_a, feats.q_b,
                feats.G_E, feats.N, noise.sigma_q_xy, noise.sigma_h_m * np.sqrt(scale),
                noise.sigma_qa_xy)
            np.testing.assert_allclose(built.Sigma_f, reference, rtol=1e-10,
                                       atol=1e-14 * np.abs(reference).max())
            basis = cdtm_math.orthonormal_complement(feats.q_b)
            Sigma_e = cdtm_math.residual_covariance(reference, basis)
            np.testing.assert_allclose(built.basis_b, basis, rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(built.Sigma_e, Sigma_e, rtol=1e-10,
                                       atol=1e-14 * np.abs(Sigma_e).max())
            np.testing.assert_allclose(built.sqrt_info, cdtm_math.sqrt_information(Sigma_e),
                                       rtol=1e-8)
            if qa_noise is not None:  # the kernel's scale: the measured residual's spread
                measured = built.whitened_full_covariance()
                T = built.sqrt_info @ np.linalg.inv(built.sqrt_info_full)
                np.testing.assert_allclose(measured, T @ np.swapaxes(T, 1, 2), rtol=1e-10,
                                           atol=1e-14)
                np.testing.assert_allclose(
                    built.robust_scale,
                    np.sqrt(np.maximum(0.5 * np.trace(measured, axis1=1, axis2=2), 1.0)),
                    rtol=1e-10)


def test_normalized_residuals_are_the_mahalanobis_distances_as_measured(manifold, rng):
    """``e^T Sigma_full^-1 e`` of the unwhitened residual: the factor's whitening undone and
    the measured noise's (both observations' pixels and the DTM) applied."""
    for _ in range(10):
        body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, pixel_noise=5e-3)
        factor = CdtmPairFactor(X(0), X(1), feats, body_T_cam)
        d = factor.normalized_residuals(Ta, Tb)
        raw = np.linalg.solve(feats.sqrt_info, factor.whitened_residuals(Ta, Tb)[..., None])
        Sigma_full = np.linalg.inv(np.swapaxes(feats.sqrt_info_full, 1, 2)
                                   @ feats.sqrt_info_full)
        expected = (np.swapaxes(raw, 1, 2) @ np.linalg.solve(Sigma_full, raw))[:, 0, 0]
        assert d.min() > 0
        np.testing.assert_allclose(d, expected, rtol=1e-9)


def test_innovation_spread_under_a_pose_prior_is_H_P_Ht(manifold, rng):
    """Poses drawn from a joint prior P on GTSAM's tangent spaces (Pose3.retract, the
    convention of its marginals) spread the innovations as H P H^T: what the innovation
    gate assumes of H from ``innovations`` and P from iSAM2."""
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, n=12, pixel_noise=0.0)
    factor = CdtmPairFactor(X(0), X(1), feats, body_T_cam)
    e0, H_a, H_b = factor.innovations(Ta, Tb)
    L = rng.normal(size=(12, 12)) * 1e-4  # correlations, under pose b's own spread
    P = L @ L.T + np.diag(np.r_[[1e-8] * 3, [1e-4] * 3, [1e-6] * 3, [4e-3] * 3])
    xi = rng.multivariate_normal(np.zeros(12), P, N_PRIOR_DRAWS)
    de = np.array([factor.innovations(gtsam.Pose3(Ta).retract(x[:6]).matrix(),
                                      gtsam.Pose3(Tb).retract(x[6:]).matrix())[0] - e0
                   for x in xi])  # (draws, n, 2)
    H = np.concatenate([H_a, H_b], axis=2)
    predicted = H @ P @ np.swapaxes(H, 1, 2)  # (n, 2, 2)
    empirical = np.einsum("dni,dnj->nij", de, de) / N_PRIOR_DRAWS
    scale = np.sqrt(np.einsum("nii->n", predicted))[:, None, None]
    np.testing.assert_allclose(empirical / scale**2, predicted / scale**2, atol=SPREAD_TOL)


def test_a_pair_factor_lives_as_long_as_a_graph_holds_it_and_no_longer(manifold, rng):
    """Catches the cycle through GTSAM (the factor holding its ``CustomFactor`` strongly,
    whose C++ callback holds the factor): Python's collector cannot see it, and every pair
    factor of every run stayed in memory (+240 MB a 1000-frame batch, 2026-11-27). Also
    catches the opposite break, a callback that would not keep its factor alive: a graph
    the only holder must still evaluate it."""
    import gc
    import weakref

    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, n=40)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(Ta))
    values.insert(X(1), gtsam.Pose3(Tb))
    pair = CdtmPairFactor(X(0), X(1), feats, body_T_cam)
    expected = pair.factor.error(values)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(pair.factor)
    alive = weakref.ref(pair)
    del pair
    gc.collect()
    assert alive() is not None  # the graph's factor holds it
    assert graph.error(values) == pytest.approx(expected, rel=1e-12)
    del graph
    gc.collect()
    assert alive() is None


def test_a_factor_refreshed_on_another_reading_of_the_map_is_the_one_built_there(manifold,
                                                                                  rng):
    """``refreshed`` given another map's noise and ray caster (a map found worse
    mid-flight: a grown sigma_h, regional slopes) equals a factor built afresh at the same
    poses with them; given its own, it is ``refreshed`` as before. Mutations tried
    (2026-11-28): the old caster's planes kept (``self.planes`` for ``source.planes``) ->
    the residuals differ; the factor's own noise kept -> ``Sigma_f`` differs; a fixed-plane
    factor's planes kept (the review's find) -> its normals differ: each fails."""
    terrain = manifold.WavyTerrain(amplitude_m=60.0, wavelength_m=400.0)
    other = manifold.WavyTerrain(amplitude_m=40.0, wavelength_m=300.0)
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain)

    def caster(t):
        return lambda origin, ray: t.raycast(np.broadcast_to(origin, ray.shape), ray)

    f = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.REINTERSECT, caster(terrain))
    moved = Ta @ make_pose(np.eye(3), [30.0, -20.0, 5.0])
    f.evaluate(moved, Tb)  # (its planes cast at the pose: none of them may be kept)
    assert feats.noise is not None
    grown = FeatureNoise(feats.noise.sigma_q_xy, 3.0 * feats.noise.sigma_h_m)
    on = f.refreshed(moved, Tb, grown, caster(other))
    wTc_a, wTc_b = moved @ body_T_cam, Tb @ body_T_cam
    G_E, N, valid = caster(other)(wTc_a[:3, 3], feats.q_a @ wTc_a[:3, :3].T)
    assert valid.all()
    built = PairFeatures.build(wTc_a, wTc_b, feats.q_a, feats.q_b, G_E, N, grown,
                               feats.dtm_variance_scale)
    fresh = CdtmPairFactor(X(0), X(1), built, body_T_cam, PlaneMode.REINTERSECT, caster(other))
    np.testing.assert_allclose(on.features.Sigma_f, built.Sigma_f, rtol=1e-12)
    np.testing.assert_allclose(on.evaluate(moved, Tb)[0], fresh.evaluate(moved, Tb)[0],
                               rtol=1e-12, atol=1e-12)
    # a factor whose planes are fixed takes the other map's too (cast once, here)
    fixed = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.FIXED)
    np.testing.assert_array_equal(fixed.refreshed(moved, Tb, grown, caster(other)).features.N, N)
    same = f.refreshed(moved, Tb, feats.noise, caster(terrain))
    np.testing.assert_allclose(same.evaluate(moved, Tb)[0], f.refreshed(moved, Tb).evaluate(
        moved, Tb)[0], rtol=1e-12, atol=1e-12)
