"""Closed-form analysis (eqs. 9-32) against numerical derivatives and GTSAM's marginals."""

from __future__ import annotations

import numpy as np
import pytest

from cdtm_graph.analysis import closed_form as analysis
from cdtm_graph.analysis.two_frame import TwoFrameSettings, solve_two_frame
from cdtm_graph.geometry import make_pose
from factors import FeatureNoise, cdtm_math

#: Exact derivatives vs central differences (step 1e-6).
DERIVATIVE_RTOL = 1e-6
#: GTSAM's marginal vs the weighted eq. 13: same linear algebra up to rounding.
MARGINAL_RTOL = 1e-6
NOISE = FeatureNoise(sigma_q_xy=(0.5 / 346.4, 0.5 / 346.4), sigma_h_m=2.4)


@pytest.fixture
def nominal_pair(manifold):
    """Factory: A noiseless pair over 300 m relief: 40 m baseline, ~10 deg rotation, ~60 deg FOV."""
    def make(rng, n=170, altitude_m=500.0, half_fov=0.5):
        """A noiseless pair over 300 m relief: 40 m baseline, ~10 deg rotation, ~60 deg FOV."""
        terrain = manifold.WavyTerrain(amplitude_m=150.0, wavelength_m=1100.0, base_m=0.0)
        body_T_cam = manifold.downward_body_T_cam(rng)
        Ta = make_pose(
            manifold.random_rotation(rng, 0.1), np.r_[rng.uniform(-300, 300, 2), altitude_m + 150]
        )
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        from cdtm_graph.geometry import so3_exp

        step_dir = rng.normal(size=3) * np.r_[1, 1, 0.2]
        Tb = Ta @ make_pose(
            so3_exp(axis * np.radians(10)), 40 * step_dir / np.linalg.norm(step_dir)
        )
        wTc_a, wTc_b = Ta @ body_T_cam, Tb @ body_T_cam
        q_a = np.c_[rng.uniform(-half_fov, half_fov, (n, 2)), np.ones(n)]
        ray = q_a @ wTc_a[:3, :3].T
        G, N, valid = terrain.raycast(np.broadcast_to(wTc_a[:3, 3], ray.shape), ray)
        g_b = (G - wTc_b[:3, 3]) @ wTc_b[:3, :3]
        q_b = g_b / g_b[:, 2:3]
        keep = valid & (np.abs(q_b[:, :2]) < 0.6).all(axis=1)
        return terrain, body_T_cam, Ta, Tb, q_a[keep], q_b[keep], G[keep], N[keep]

    return make


def test_euler_convention_round_trip_and_derivatives(manifold, rng):
    for _ in range(50):
        angles = rng.uniform(-1.2, 1.2, 3)
        R = analysis.rotation_from_euler(angles)
        np.testing.assert_allclose(analysis.euler_from_rotation(R), angles, atol=1e-12)
        # R^T = Rz(psi) Ry(theta) Rx(phi): eq. 30 reads theta = asin(-R13)
        np.testing.assert_allclose(np.arcsin(-R[0, 2]), angles[1], atol=1e-12)
        dR = analysis.rotation_euler_derivatives(angles)
        num = manifold.numerical_jacobian(lambda a: analysis.rotation_from_euler(a).ravel(), angles)
        np.testing.assert_allclose(dR.reshape(3, 9).T, num, atol=DERIVATIVE_RTOL)


def test_theta_round_trip_and_c2_jacobian(manifold, rng):
    for _ in range(50):
        theta = np.r_[rng.normal(0, 100, 3), rng.uniform(-1, 1, 3), rng.normal(0, 30, 3),
                      rng.uniform(-0.3, 0.3, 3)]
        Ta, Tb = analysis.cameras_from_theta(theta)
        np.testing.assert_allclose(analysis.theta_from_cameras(Ta, Tb), theta, atol=1e-10)

        def c2(th):
            _, T2 = analysis.cameras_from_theta(th)
            return np.r_[T2[:3, 3], analysis.euler_from_rotation(T2[:3, :3])]

        num = manifold.numerical_jacobian(c2, theta)
        J = analysis.jacobian_c2(theta)
        assert np.abs(J - num).max() < DERIVATIVE_RTOL * np.abs(num).max()


def test_theta_jacobian_wrt_body_tangents(manifold, rng):
    for _ in range(50):
        body_T_cam = manifold.downward_body_T_cam(rng)
        Ta = make_pose(manifold.random_rotation(rng, 0.5), rng.normal(0, 100, 3))
        Tb = Ta @ make_pose(manifold.random_rotation(rng, 0.3), rng.normal(0, 30, 3))
        H = analysis.theta_jacobian_wrt_body_tangents(Ta, Tb, body_T_cam)

        def theta_of(A, B):
            return analysis.theta_from_cameras(A @ body_T_cam, B @ body_T_cam)

        num = np.c_[manifold.numerical_pose_jacobian(lambda A: theta_of(A, Tb), Ta),
                    manifold.numerical_pose_jacobian(lambda B: theta_of(Ta, B), Tb)]
        assert np.abs(H - num).max() < DERIVATIVE_RTOL * np.abs(num).max()


def test_jacobian_theta_eqs_15_to_18_match_central_differences(nominal_pair, manifold, rng):
    _, body_T_cam, Ta, Tb, q_a, q_b, G, N = nominal_pair(rng, n=20)
    q_b = q_b + np.c_[rng.normal(0, 3e-3, (len(q_b), 2)), np.zeros(len(q_b))]
    theta = analysis.theta_from_cameras(Ta @ body_T_cam, Tb @ body_T_cam)
    J = analysis.jacobian_theta(theta, q_a, q_b, G, N).reshape(-1, 12)

    def F(th):
        A, B = analysis.cameras_from_theta(th)
        return cdtm_math.paper_residual(A[:3, :3], A[:3, 3], B[:3, :3], B[:3, 3],
                                        q_a, q_b, G, N)[0].ravel()

    num = manifold.numerical_jacobian(F, theta)
    assert np.abs(J - num).max() < DERIVATIVE_RTOL * np.abs(num).max()


def test_gtsam_marginal_equals_weighted_eq13_and_unweighted_is_larger(nominal_pair, rng):
    for _ in range(5):
        terrain, body_T_cam, Ta, Tb, q_a, q_b, G, N = nominal_pair(rng)
        result = solve_two_frame(q_a, q_b, terrain.raycast, Ta, Tb, body_T_cam, NOISE)
        # noiseless data: the solve stays at the truth, where the closed form is evaluated
        a = result.analysis
        np.testing.assert_allclose(result.sigma_theta_gtsam, a.sigma_theta_weighted,
                                   rtol=MARGINAL_RTOL,
                                   atol=MARGINAL_RTOL
                                   * np.abs(np.diag(a.sigma_theta_weighted)).min())
        gap = np.linalg.eigvalsh(a.sigma_theta_unweighted - a.sigma_theta_weighted)
        assert gap.min() > -1e-9 * np.abs(a.sigma_theta_weighted).max()
        gap_c2 = np.linalg.eigvalsh(a.sigma_c2_unweighted - a.sigma_c2_weighted)
        assert gap_c2.min() > -1e-9 * np.abs(a.sigma_c2_weighted).max()
        # The two differ (the printed eq. 13 is not the weighted estimator's covariance).
        assert gap.max() > 1e-3 * np.abs(a.sigma_theta_weighted).max()


@pytest.mark.parametrize("case", ["few_features", "narrow_fov", "short_baseline", "flat_terrain"])
def test_each_degeneracy_is_detected_and_named(nominal_pair, rng, case):
    half_fov = np.tan(np.radians(2.5)) if case == "narrow_fov" else 0.5
    terrain, body_T_cam, Ta, Tb, q_a, q_b, G, N = nominal_pair(rng, half_fov=half_fov)
    settings = analysis.DegeneracySettings()
    wTc_a, wTc_b = Ta @ body_T_cam, Tb @ body_T_cam
    if case == "few_features":
        q_a, G = q_a[:5], G[:5]
    elif case == "short_baseline":
        wTc_b = wTc_b.copy()
        wTc_b[:3, 3] = wTc_a[:3, 3] + 0.3 * (wTc_b[:3, 3] - wTc_a[:3, 3]) / 40
    else:
        G = G.copy()
        G[:, 2] = 0.01 * G[:, 0] + rng.normal(0, 0.1, len(G))
    verdict = analysis.geometric_degeneracy(wTc_a, wTc_b, q_a, G, NOISE.sigma_h_m, settings)
    assert verdict.reasons[0] == case
    # A 5x5-degree camera sees a small, nearly planar patch: it may be flat as well.
    assert set(verdict.reasons[1:]) <= ({"flat_terrain"} if case == "narrow_fov" else set())
    assert case in verdict.message()


def test_nominal_geometry_is_not_degenerate(nominal_pair, rng):
    terrain, body_T_cam, Ta, Tb, q_a, q_b, G, N = nominal_pair(rng)
    a = analysis.analyze_pair(Ta @ body_T_cam, Tb @ body_T_cam, q_a, q_b, G, N, NOISE)
    assert not a.degeneracy.degenerate, a.degeneracy.message()
    assert np.isfinite(a.condition_number)


def test_solve_raises_on_degenerate_geometry_and_flags_when_asked(nominal_pair, manifold, rng):
    from cdtm_graph.errors import DegenerateGeometryError

    terrain, body_T_cam, Ta, Tb, q_a, q_b, G, N = nominal_pair(rng)
    with pytest.raises(DegenerateGeometryError) as err:
        solve_two_frame(q_a[:5], q_b[:5], terrain.raycast, Ta, Tb, body_T_cam, NOISE)
    assert err.value.reasons == ("few_features",)
    flat = manifold.WavyTerrain(amplitude_m=0.0)
    ray = q_a @ (Ta @ body_T_cam)[:3, :3].T
    Gf, _, _ = flat.raycast(np.broadcast_to((Ta @ body_T_cam)[:3, 3], ray.shape), ray)
    g_b = (Gf - (Tb @ body_T_cam)[:3, 3]) @ (Tb @ body_T_cam)[:3, :3]
    result = solve_two_frame(q_a, g_b / g_b[:, 2:3], flat.raycast, Ta, Tb, body_T_cam, NOISE,
                             TwoFrameSettings(raise_on_degenerate=False))
    assert "flat_terrain" in result.degeneracy.reasons
