"""Online camera calibration: the factor's calibration Jacobians, config keys, and the
faults it is for (focal length, mount, time offset) recovered on simulated flights."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from factors import CdtmPairFactor, PlaneMode, RobustKernel
from factors.calibration import CALIBRATION_DIM, CalibrationLink
from tests.manifold import WavyTerrain, numerical_jacobian, numerical_pose_jacobian
from tests.test_cdtm_factor import random_pair

N_CONFIGURATIONS = 30
#: Central differences with a 1e-6 step agree with exact derivatives to ~1e-9 relative;
#: the factor's own focal-scale column is a central difference too (step 1e-5).
JACOBIAN_RTOL = 1e-5


def _random_calibration(rng) -> np.ndarray:
    return np.r_[rng.uniform(-0.05, 0.05), np.radians(rng.uniform(-1, 1, 3)),
                 rng.uniform(-0.02, 0.02)]


def _link(rng, key=None, value=None) -> CalibrationLink:
    twist = lambda: np.r_[rng.normal(0, 0.1, 3), rng.normal(0, 60, 3)]  # noqa: E731
    return CalibrationLink(key, twist(), twist(),
                           np.zeros(CALIBRATION_DIM) if value is None else value)


@pytest.mark.parametrize("mode", [PlaneMode.FIXED, PlaneMode.REINTERSECT])
def test_calibration_and_pose_jacobians_match_central_differences(rng, mode):
    worst = 0.0
    for _ in range(N_CONFIGURATIONS):
        terrain = WavyTerrain(amplitude_m=rng.uniform(10, 60), wavelength_m=rng.uniform(300, 900))
        body_T_cam, Ta, Tb, feats = random_pair(rng, terrain)
        fac = CdtmPairFactor(X(0), X(1), feats, body_T_cam, mode, raycast=terrain.raycast,
                             calibration=_link(rng, gtsam.symbol("C", 0)))
        c = _random_calibration(rng)

        def residual(Ta=Ta, Tb=Tb, c=c, fac=fac):
            return fac.evaluate_calibrated(Ta, Tb, c, want_jacobians=False)[0].ravel()

        _, Ha, Hb, Hc = fac.evaluate_calibrated(Ta, Tb, c)
        num_a = numerical_pose_jacobian(lambda T: residual(Ta=T), Ta)
        num_b = numerical_pose_jacobian(lambda T: residual(Tb=T), Tb)
        num_c = numerical_jacobian(lambda x: residual(c=x), c)
        for exact, num in ((Ha.reshape(-1, 6), num_a), (Hb.reshape(-1, 6), num_b),
                           (Hc.reshape(-1, CALIBRATION_DIM), num_c)):
            # each column on its own scale (seconds, radians and a scale factor differ)
            scale = np.maximum(np.abs(num).max(axis=0), 1e-12)
            worst = max(worst, float((np.abs(exact - num).max(axis=0) / scale).max()))
    assert worst < JACOBIAN_RTOL


def test_zero_calibration_leaves_the_factor_unchanged(rng):
    """At the nominal (zero) calibration the residual and pose Jacobians are the
    factor's without a calibration."""
    terrain = WavyTerrain(amplitude_m=40.0, wavelength_m=600.0)
    body_T_cam, Ta, Tb, feats = random_pair(rng, terrain)
    plain = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.REINTERSECT,
                           raycast=terrain.raycast, robust=RobustKernel.CAUCHY)
    linked = plain.with_calibration(_link(rng, gtsam.symbol("C", 0)))
    e0, Ha0, Hb0 = (a.copy() for a in plain.evaluate(Ta, Tb))
    e1, Ha1, Hb1, _ = linked.evaluate_calibrated(Ta, Tb, np.zeros(CALIBRATION_DIM))
    np.testing.assert_allclose(e1, e0, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(Ha1, Ha0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(Hb1, Hb0, rtol=1e-12, atol=1e-12)


def test_robust_rows_weigh_the_calibration_columns_alike(rng):
    """With a kernel, every Jacobian row is the plain one times the feature's sqrt
    weight (GTSAM's robust linearization), the calibration's included."""
    terrain = WavyTerrain(amplitude_m=40.0, wavelength_m=600.0)
    body_T_cam, Ta, Tb, feats = random_pair(rng, terrain, pixel_noise=2e-2)
    link = _link(rng, gtsam.symbol("C", 0))
    c = _random_calibration(rng)
    robust = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.FIXED,
                            robust=RobustKernel.CAUCHY, robust_threshold=0.5, calibration=link)
    e_r, Ha_r, _, Hc_r = robust.evaluate_calibrated(Ta, Tb, c)
    e_p, Ha_p, _, Hc_p = robust.evaluate_calibrated(Ta, Tb, c, robust=False)
    sw = np.linalg.norm(e_r, axis=1) / np.linalg.norm(e_p, axis=1)
    assert sw.min() < 0.9  # the kernel is active
    np.testing.assert_allclose(Ha_r, sw[:, None, None] * Ha_p, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(Hc_r, sw[:, None, None] * Hc_p, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("n", [4, 40])
def test_gtsam_linearization_holds_the_calibration_block(rng, n):
    """Short pairs give GTSAM the raw rows, tall ones a triangle with the same Hessian
    and gradient over [X(a), X(b), C(0)]."""
    terrain = WavyTerrain(amplitude_m=40.0, wavelength_m=600.0)
    body_T_cam, Ta, Tb, feats = random_pair(rng, terrain, n=n)
    key = gtsam.symbol("C", 0)
    fac = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.FIXED,
                         calibration=_link(rng, key))
    c = _random_calibration(rng)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(Ta))
    values.insert(X(1), gtsam.Pose3(Tb))
    values.insert(key, c)
    A, b = fac.factor.linearize(values).jacobian()
    e, Ha, Hb, Hc = fac.evaluate_calibrated(Ta, Tb, c)
    H = np.concatenate([Ha.reshape(-1, 6), Hb.reshape(-1, 6),
                        Hc.reshape(-1, CALIBRATION_DIM)], axis=1)
    np.testing.assert_allclose(A.T @ A, H.T @ H, rtol=1e-8, atol=1e-8 * np.abs(H.T @ H).max())
    np.testing.assert_allclose(A.T @ b, -H.T @ e.ravel(), rtol=1e-8,
                               atol=1e-8 * np.abs(H.T @ e.ravel()).max())
    np.testing.assert_allclose(fac.factor.error(values), 0.5 * np.sum(e ** 2), rtol=1e-10)
