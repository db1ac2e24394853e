"""WGS84 geodesy: local frame conversions, normal gravity, Earth rate, EGM96 geoid."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cdtm_graph import geodesy as G
from cdtm_graph.geodesy import GeodesyError, GeodeticOrigin, LocalFrame

ORIGIN = GeodeticOrigin(36.5, 127.25, 120.0)

#: Round trips world -> geodetic -> world over 100 km must close to this (m).
ROUND_TRIP_TOL_M = 1e-3
#: Normal gravity against the gradient of the closed-form normal potential (m/s^2): the
#: second-order height series and Groves' north term are approximations.
GRAVITY_TOL_1KM_MPS2 = 2e-7
GRAVITY_TOL_20KM_MPS2 = 2e-6
#: Our bilinear EGM96 against NGA's INTPT reference values (m); measured 0.3-5.7 cm.
EGM96_TOL_M = 0.06


def _normal_potential(p_ecef: np.ndarray) -> np.ndarray:
    """WGS84 normal gravity potential (gravitation + centrifugal) in closed form.

    Heiskanen & Moritz, Physical Geodesy, eq. 2-126, in ellipsoidal coordinates (u, beta).
    """
    a, b = G.WGS84_A_M, G.WGS84_B_M
    e_lin = math.sqrt(a * a - b * b)
    omega, gm = G.WGS84_OMEGA_RADPS, G.WGS84_GM_M3PS2

    def q(u):
        return 0.5 * ((1 + 3 * u * u / e_lin**2) * np.arctan(e_lin / u) - 3 * u / e_lin)

    x, y, z = p_ecef[..., 0], p_ecef[..., 1], p_ecef[..., 2]
    s = x * x + y * y + z * z - e_lin**2
    u2 = 0.5 * s * (1 + np.sqrt(1 + 4 * e_lin**2 * z * z / s**2))
    u = np.sqrt(u2)
    beta = np.arctan2(z * np.sqrt(u2 + e_lin**2), u * np.hypot(x, y))
    return (gm / e_lin * np.arctan(e_lin / u)
            + 0.5 * omega**2 * a**2 * q(u) / q(b) * (np.sin(beta) ** 2 - 1 / 3)
            + 0.5 * omega**2 * (u2 + e_lin**2) * np.cos(beta) ** 2)


def _potential_gradient(p_ecef: np.ndarray, step_m: float = 300.0) -> np.ndarray:
    """Five-point central differences of the normal potential (round-off ~1e-9 m/s^2)."""
    g = np.zeros(3)
    for i in range(3):
        d = np.zeros(3)
        d[i] = step_m
        u = [_normal_potential(p_ecef + k * d) for k in (-2, -1, 1, 2)]
        g[i] = (u[0] - 8 * u[1] + 8 * u[2] - u[3]) / (12 * step_m)
    return g


def test_normal_gravity_on_the_ellipsoid_is_wgs84s_defining_values():
    assert G.normal_gravity_mps2(0.0) == pytest.approx(G.WGS84_GAMMA_EQUATOR_MPS2, abs=1e-12)
    assert G.normal_gravity_mps2(90.0) == pytest.approx(G.WGS84_GAMMA_POLE_MPS2, abs=1e-12)
    assert G.normal_gravity_mps2(-90.0) == pytest.approx(G.WGS84_GAMMA_POLE_MPS2, abs=1e-12)


@pytest.mark.parametrize("latitude_deg", [0.0, 20.0, 45.0, -63.0, 89.9])
def test_normal_gravity_vector_is_the_gradient_of_the_normal_potential(latitude_deg):
    for height_m, tol in ((0.0, GRAVITY_TOL_1KM_MPS2), (1000.0, GRAVITY_TOL_1KM_MPS2),
                          (5000.0, GRAVITY_TOL_20KM_MPS2), (20000.0, GRAVITY_TOL_20KM_MPS2)):
        p = G.geodetic_to_ecef(latitude_deg, 10.0, height_m)[0]
        reference = G.enu_R_ecef(latitude_deg, 10.0)[0] @ _potential_gradient(p)
        ours = G.normal_gravity_enu_mps2(latitude_deg, height_m)[0]
        np.testing.assert_allclose(ours, reference, rtol=0, atol=tol,
                                   err_msg=f"lat {latitude_deg}, h {height_m}")


def test_gravity_in_the_world_follows_the_local_vertical(rng):
    frame = LocalFrame(ORIGIN)
    # At the origin, on the ellipsoid's normal: straight down the world's -z.
    g0 = frame.gravity_world_mps2(np.zeros(3))[0]
    np.testing.assert_allclose(g0[[0, 2]], [0.0, -G.normal_gravity_mps2(36.5, 120.0)],
                               rtol=0, atol=1e-12)
    # Elsewhere: along the ellipsoid normal at the point (the ECEF normal, computed here
    # from latitude and longitude directly), up to the north term of the normal field.
    p_world = np.column_stack([rng.uniform(-50e3, 50e3, 20), rng.uniform(-50e3, 50e3, 20),
                               rng.uniform(-200.0, 3000.0, 20)])
    lat, lon, h = frame.world_to_geodetic(p_world)
    la, lo = np.radians(lat), np.radians(lon)
    normal_ecef = np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
    down_world = -normal_ecef @ frame.world_R_ecef.T
    g = frame.gravity_world_mps2(p_world)
    along = np.einsum("ni,ni->n", g, down_world)
    np.testing.assert_allclose(along, G.normal_gravity_mps2(lat, h), rtol=1e-12)
    across = np.linalg.norm(g - along[:, None] * down_world, axis=1)
    assert np.all(across <= 8.1e-9 * np.abs(h) + 1e-12)
    # The local vertical turns by the distance over the Earth's radius: 0.45 deg at 50 km.
    far = frame.gravity_world_mps2(np.array([0.0, 50e3, 0.0]))[0]
    tilt_deg = math.degrees(math.atan2(-far[1], -far[2]))
    assert tilt_deg == pytest.approx(math.degrees(50e3 / 6.36e6), rel=0.01)


def test_world_and_geodetic_round_trip_to_a_millimetre_over_100_km(rng):
    frame = LocalFrame(ORIGIN)
    p = np.column_stack([rng.uniform(-100e3, 100e3, 1000), rng.uniform(-100e3, 100e3, 1000),
                         rng.uniform(-1000.0, 10e3, 1000)])
    back = frame.geodetic_to_world(*frame.world_to_geodetic(p))
    assert np.abs(back - p).max() < ROUND_TRIP_TOL_M


def test_world_frame_agrees_with_projs_topocentric_conversion(rng):
    from pyproj import Transformer

    frame = LocalFrame(ORIGIN)
    topo = Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        "+step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={ORIGIN.latitude_deg} "
        f"+lon_0={ORIGIN.longitude_deg} +h_0={ORIGIN.height_m}")
    lat = ORIGIN.latitude_deg + rng.uniform(-0.9, 0.9, 200)
    lon = ORIGIN.longitude_deg + rng.uniform(-1.1, 1.1, 200)
    h = rng.uniform(-100.0, 9000.0, 200)
    reference = np.column_stack(topo.transform(lon, lat, h))
    assert np.abs(frame.geodetic_to_world(lat, lon, h) - reference).max() < ROUND_TRIP_TOL_M


def test_the_ground_curves_below_the_tangent_plane():
    frame = LocalFrame(GeodeticOrigin(36.5, 127.0, 0.0))
    # 29 km due north on the ellipsoid: about d^2 / (2 M) below the plane (M: meridian
    # radius of curvature), the 67 m.
    m_radius = (G.WGS84_A_M * (1 - G.WGS84_E2)
                / (1 - G.WGS84_E2 * math.sin(math.radians(36.5)) ** 2) ** 1.5)
    lat = 36.5 + math.degrees(29e3 / m_radius)
    p = frame.geodetic_to_world(lat, 127.0, 0.0)[0]
    assert p[1] == pytest.approx(29e3, rel=1e-3)
    assert p[2] == pytest.approx(-p[1] ** 2 / (2 * m_radius), rel=1e-3)
    assert -68.0 < p[2] < -65.0


def test_earth_rate_in_the_world_frame():
    frame = LocalFrame(ORIGIN)
    lat = math.radians(ORIGIN.latitude_deg)
    np.testing.assert_allclose(frame.earth_rate_world_radps,
                               G.WGS84_OMEGA_RADPS * np.array([0.0, math.cos(lat),
                                                               math.sin(lat)]),
                               rtol=0, atol=1e-18)
    env = frame.imu_environment(np.array([1000.0, -2000.0, 500.0]))
    np.testing.assert_array_equal(env.earth_rate_radps, frame.earth_rate_world_radps)
    np.testing.assert_allclose(env.gravity_mps2,
                               frame.gravity_world_mps2(np.array([1000.0, -2000.0, 500.0]))[0])


def test_states_round_trip_through_the_local_enu(rng):
    frame = LocalFrame(ORIGIN)
    n = 50
    lat = ORIGIN.latitude_deg + rng.uniform(-0.4, 0.4, n)
    lon = ORIGIN.longitude_deg + rng.uniform(-0.5, 0.5, n)
    h = rng.uniform(0.0, 3000.0, n)
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    v = rng.uniform(-250.0, 250.0, (n, 3))
    p_w, q_w, v_w = frame.states_from_geodetic(lat, lon, h, q, v)
    # Speeds and the body's vertical axis against the point's own "up" are frame-free.
    np.testing.assert_allclose(np.linalg.norm(v_w, axis=1), np.linalg.norm(v, axis=1))
    from cdtm_graph.geometry import quat_wxyz_to_rotation
    up_world = frame.world_R_enu(lat, lon)[:, :, 2]
    body_z_world = quat_wxyz_to_rotation(q_w)[:, :, 2]
    np.testing.assert_allclose(np.einsum("ni,ni->n", up_world, body_z_world),
                               quat_wxyz_to_rotation(q)[:, 2, 2], atol=1e-12)
    lat2, lon2, h2, q2, v2 = frame.states_to_geodetic(p_w, quat_wxyz_to_rotation(q_w), v_w)
    np.testing.assert_allclose(lat2, lat, atol=1e-10)
    np.testing.assert_allclose(lon2, lon, atol=1e-10)
    np.testing.assert_allclose(h2, h, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.sum(q2 * q, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(v2, v, atol=1e-9)
    # At the origin the local ENU is the world.
    np.testing.assert_allclose(frame.world_R_enu(ORIGIN.latitude_deg, ORIGIN.longitude_deg)[0],
                               np.eye(3), atol=1e-15)


#: NGA's test values for the EGM96 15' grid (readme of the EGM96 distribution, INTPT.F):
#: latitude, longitude (0..360), geoid height (m).
NGA_EGM96_TEST_VALUES = [
    (38.6281550, 269.7791550, -31.628),
    (-14.6212170, 305.0211140, -2.969),
    (46.8743190, 102.4487290, -43.575),
    (-23.6174460, 133.8747120, 15.871),
    (38.6254730, 359.9995000, 50.066),
    (-0.4667440, 0.0023000, 17.329),
]


def test_egm96_undulation_matches_ngas_published_values():
    lat, lon, expected = np.array(NGA_EGM96_TEST_VALUES).T
    # Longitudes given either way round the globe give the same heights.
    np.testing.assert_allclose(G.geoid_undulation_m(lat, lon), expected, rtol=0,
                               atol=EGM96_TOL_M)
    np.testing.assert_allclose(G.geoid_undulation_m(lat, (lon + 180) % 360 - 180), expected,
                               rtol=0, atol=EGM96_TOL_M)


def test_missing_geoid_grid_is_one_clear_error(monkeypatch, tmp_path):
    monkeypatch.setenv(G.EGM96_GRID_ENV, str(tmp_path / "nowhere.tif"))
    with pytest.raises(GeodesyError, match="EGM96 geoid grid not found"):
        G.geoid_undulation_m(10.0, 10.0)


@pytest.mark.parametrize("kwargs, message", [
    ({"latitude_deg": 91.0, "longitude_deg": 0.0, "height_m": 0.0}, "latitude_deg"),
    ({"latitude_deg": 0.0, "longitude_deg": 400.0, "height_m": 0.0}, "longitude_deg"),
    ({"latitude_deg": 0.0, "longitude_deg": 0.0, "height_m": float("nan")}, "height_m"),
])
def test_origin_out_of_range_is_refused(kwargs, message):
    with pytest.raises(GeodesyError, match=message):
        GeodeticOrigin(**kwargs)


def _gtsam_drift(frame: LocalFrame, p_world: np.ndarray, compensate: bool) -> float:
    """How far GTSAM predicts a perfect IMU at rest on the Earth to move in 2 s (m)."""
    import gtsam

    env = frame.imu_environment(p_world)
    gravity = env.gtsam_n_gravity(p_world) if compensate else env.gravity_mps2
    params = gtsam.PreintegrationParams(gravity)
    for set_cov in (params.setAccelerometerCovariance, params.setGyroscopeCovariance,
                    params.setIntegrationCovariance):
        set_cov(1e-8 * np.eye(3))
    params.setOmegaCoriolis(env.earth_rate_radps)
    bias = gtsam.imuBias.ConstantBias()
    pim = gtsam.PreintegratedImuMeasurements(params, bias)
    for _ in range(200):  # level, axes along the world's: reads -g and the Earth rate
        pim.integrateMeasurement(-env.gravity_mps2, env.earth_rate_radps, 0.01)
    state = pim.predict(gtsam.NavState(gtsam.Rot3(), p_world, np.zeros(3)), bias)
    return float(np.linalg.norm(state.position() - p_world))


def test_gtsam_n_gravity_keeps_a_resting_imu_at_rest_far_from_the_origin():
    # GTSAM 4.3 adds -Omega x (Omega x p) itself; normal gravity holds the centrifugal
    # term already, so gtsam_n_gravity takes it out again. Without that, 36 km from the
    # origin a resting IMU moves 0.3 mm in 2 s (2.6 m after 240 s of flight).
    frame = LocalFrame(ORIGIN)
    far = np.array([30000.0, -20000.0, 500.0])
    at_origin = _gtsam_drift(frame, np.zeros(3), compensate=True)
    assert _gtsam_drift(frame, far, compensate=True) < at_origin + 1e-7
    assert at_origin < 1e-5  # GTSAM's hold of the samples over their steps
    assert _gtsam_drift(frame, far, compensate=False) > 2e-4
