"""Tests of cdtm_graph.camera: projection, undistortion, FOV, validation."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cdtm_graph.camera import DistortionModel, PinholeCamera

ROUND_TRIP_TOL_PX = 1e-6      # the brief's bound for pixels -> rays -> pixels
OPENCV_AGREEMENT_TOL_PX = 1e-9  # same formula as cv2.projectPoints, float rounding only
FOV_TOL_DEG = 1e-9

# EuRoC MH cam0 (Kalibr): strong barrel distortion, the realistic hard case.
EUROC_CAM0 = PinholeCamera(752, 480, 458.654, 457.296, 367.215, 248.375,
                           (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05))
# A milder lens with a k3 term (5 coefficients) and an off-centre principal point.
MILD_K3 = PinholeCamera(640, 512, 520.0, 518.0, 322.3, 251.7,
                        (-0.12, 0.03, 8e-4, -5e-4, -0.004))

# TUM-VI cam0 (Kalibr pinhole-equidistant): a 195-degree fisheye, whose image corners see
# beyond 90 degrees from the optical axis.
TUMVI_FISHEYE = PinholeCamera(512, 512, 190.97847715128717, 190.9733070521226,
                              254.93170605935475, 256.8974428996504,
                              (0.0034823894022493434, 0.0007150348452162257,
                               -0.0020532361418706202, 0.00020293673591811182), "equidistant")
# The equidistant model on an ordinary 60-degree aerial camera (theta instead of tan theta:
# 10% compression at the image edge) with a little k1.
NARROW_EQUIDISTANT = PinholeCamera(400, 300, 346.4, 345.0, 201.3, 148.9,
                                   (0.02, -0.004, 0.0, 0.0), "equidistant")


def _grid_over_image(cam: PinholeCamera, n_u: int = 121, n_v: int = 97) -> np.ndarray:
    """(N, 2) pixels covering the whole image, outer pixel edges and corners included."""
    u, v = np.meshgrid(np.linspace(-0.5, cam.width - 0.5, n_u),
                       np.linspace(-0.5, cam.height - 0.5, n_v))
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.mark.parametrize("cam", [EUROC_CAM0, MILD_K3], ids=["euroc_radtan4", "mild_radtan5"])
def test_round_trip_pixels_rays_pixels_over_whole_image(cam: PinholeCamera) -> None:
    uv = _grid_over_image(cam)
    rays = cam.pixels_to_rays(uv)
    assert rays.shape == (uv.shape[0], 3)
    assert np.all(rays[:, 2] == 1.0)
    assert np.all(np.isfinite(rays))
    err = np.linalg.norm(cam.rays_to_pixels(rays) - uv, axis=1)
    assert err.max() < ROUND_TRIP_TOL_PX


@pytest.mark.parametrize("cam", [EUROC_CAM0, MILD_K3], ids=["euroc_radtan4", "mild_radtan5"])
def test_distortion_actually_moves_the_rays(cam: PinholeCamera) -> None:
    # Guards the round-trip test against an undistortion that ignores distortion.
    corner = np.array([[-0.5, -0.5]])
    plain = np.array([(-0.5 - cam.cx) / cam.fx, (-0.5 - cam.cy) / cam.fy])
    assert np.linalg.norm(cam.pixels_to_rays(corner)[0, :2] - plain) > 1e-2


@pytest.mark.parametrize("cam", [EUROC_CAM0, MILD_K3], ids=["euroc_radtan4", "mild_radtan5"])
def test_rays_to_pixels_agrees_with_opencv_project_points(cam, rng) -> None:
    n = 500
    points = np.column_stack([rng.uniform(-0.8, 0.8, n), rng.uniform(-0.6, 0.6, n), np.ones(n)])
    points *= rng.uniform(0.5, 50.0, (n, 1))  # any scale, not only z = 1
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    got = cam.rays_to_pixels(points)
    np.testing.assert_allclose(got, expected.reshape(-1, 2), rtol=0, atol=OPENCV_AGREEMENT_TOL_PX)


def test_rays_behind_or_on_the_camera_plane_are_nan() -> None:
    rays = np.array([[0.1, 0.2, 1.0], [0.1, 0.2, 0.0], [0.1, 0.2, -1.0]])
    uv = EUROC_CAM0.rays_to_pixels(rays)
    assert np.all(np.isfinite(uv[0]))
    assert np.all(np.isnan(uv[1:]))


def test_from_fov_400_by_400_at_60_degrees() -> None:
    cam = PinholeCamera.from_fov(400, 400, 60.0)
    assert cam.fx == cam.fy == pytest.approx(200.0 / math.tan(math.radians(30.0)), abs=1e-12)
    assert (cam.cx, cam.cy) == (199.5, 199.5)
    h, v = cam.fov_deg
    assert h == pytest.approx(60.0, abs=FOV_TOL_DEG)
    assert v == pytest.approx(60.0, abs=FOV_TOL_DEG)
    half_diag = math.hypot(200.0, 200.0) / cam.fx
    assert cam.diagonal_fov_deg == pytest.approx(2 * math.degrees(math.atan(half_diag)),
                                                 abs=FOV_TOL_DEG)


def test_fov_of_a_non_square_image_from_intrinsics() -> None:
    cam = PinholeCamera.from_fov(640, 480, 90.0)
    h, v = cam.fov_deg
    assert h == pytest.approx(90.0, abs=FOV_TOL_DEG)
    assert v == pytest.approx(2 * math.degrees(math.atan(240.0 / 320.0)), abs=FOV_TOL_DEG)


def test_barrel_distortion_widens_the_field_of_view() -> None:
    plain = PinholeCamera(EUROC_CAM0.width, EUROC_CAM0.height, EUROC_CAM0.fx, EUROC_CAM0.fy,
                          EUROC_CAM0.cx, EUROC_CAM0.cy)
    assert EUROC_CAM0.fov_deg[0] > plain.fov_deg[0] + 5.0


@pytest.mark.parametrize("distortion", [(), (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0)])
def test_zero_distortion_equals_the_plain_pinhole_formula(distortion, rng) -> None:
    cam = PinholeCamera(400, 300, 350.0, 345.0, 201.3, 148.9, distortion)
    uv = np.column_stack([rng.uniform(-0.5, 399.5, 200), rng.uniform(-0.5, 299.5, 200)])
    rays = cam.pixels_to_rays(uv)
    np.testing.assert_allclose(rays[:, 0], (uv[:, 0] - 201.3) / 350.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rays[:, 1], (uv[:, 1] - 148.9) / 345.0, rtol=0, atol=1e-12)
    points = np.column_stack([rng.normal(size=(200, 2)), rng.uniform(0.1, 5.0, 200)])
    expected = np.column_stack([350.0 * points[:, 0] / points[:, 2] + 201.3,
                                345.0 * points[:, 1] / points[:, 2] + 148.9])
    np.testing.assert_allclose(cam.rays_to_pixels(points), expected, rtol=0, atol=1e-9)


def test_pixels_where_the_distortion_folds_over_get_nan_rays() -> None:
    # k3 < 0 with strong k1 makes the radial map non-monotonic near the far corners:
    # no ray projects there, so none may be returned.
    folding = PinholeCamera(752, 480, 458.654, 457.296, 367.215, 248.375,
                            (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, -0.01))
    rays = folding.pixels_to_rays(np.array([[751.5, 479.5], [367.0, 248.0]]))
    assert np.all(np.isnan(rays[0, :2]))
    assert np.all(np.isfinite(rays[1]))


def test_in_image_uses_the_pixel_centre_convention() -> None:
    cam = PinholeCamera.from_fov(400, 300, 60.0)
    eps = 1e-9
    uv = np.array([
        [-0.5, -0.5], [399.5, 299.5], [0.0, 0.0], [200.0, 150.0],   # inside (edges included)
        [-0.5 - eps, 10.0], [10.0, -0.5 - eps], [399.5 + eps, 10.0], [10.0, 299.5 + eps],
        [np.nan, 10.0],
    ])
    expected = np.array([True] * 4 + [False] * 5)
    np.testing.assert_array_equal(cam.in_image(uv), expected)


def test_sigma_normalized() -> None:
    cam = PinholeCamera(400, 400, 400.0, 250.0, 199.5, 199.5)
    assert cam.sigma_normalized(0.5) == (0.5 / 400.0, 0.5 / 250.0)


def test_empty_input_gives_empty_output() -> None:
    assert EUROC_CAM0.pixels_to_rays(np.zeros((0, 2))).shape == (0, 3)
    assert EUROC_CAM0.rays_to_pixels(np.zeros((0, 3))).shape == (0, 2)


@pytest.mark.parametrize("kwargs", [
    dict(width=0), dict(height=-1), dict(width=400.5), dict(width=True),
    dict(fx=0.0), dict(fy=-300.0), dict(fx=math.nan), dict(cx=math.inf), dict(fy="abc"),
    dict(distortion=(0.1, 0.2)), dict(distortion=(0.1, 0.0, 0.0, 0.0, 0.0, 0.0)),
    dict(distortion=(0.1, math.nan, 0.0, 0.0)),
])
def test_invalid_intrinsics_raise_value_error(kwargs) -> None:
    args = dict(width=400, height=300, fx=300.0, fy=300.0, cx=199.5, cy=149.5)
    args.update(kwargs)
    with pytest.raises(ValueError):
        PinholeCamera(**args)


def test_numpy_scalars_are_normalized_to_python_types() -> None:
    cam = PinholeCamera(np.int64(400), np.int32(300), np.float64(300.0), 300, 199.5, 149.5,
                        [np.float64(0.1), 0, 0, 0])
    assert type(cam.width) is int and type(cam.fy) is float
    assert cam.distortion == (0.1, 0.0, 0.0, 0.0)
    assert cam == PinholeCamera(400, 300, 300.0, 300.0, 199.5, 149.5, (0.1, 0.0, 0.0, 0.0))


# --------------------------------------------------------------------------- equidistant


@pytest.mark.parametrize("cam", [TUMVI_FISHEYE, NARROW_EQUIDISTANT], ids=["tumvi", "narrow"])
def test_equidistant_round_trip_over_the_image(cam: PinholeCamera) -> None:
    uv = _grid_over_image(cam)
    rays = cam.pixels_to_rays(uv)
    finite = np.isfinite(rays).all(axis=1)
    # Every pixel whose ray is less than 90 deg off the axis has one, and round-trips
    # (TUM-VI's theta_d is 1.554 rad at theta = 90 deg; 1.5 rad is 87 deg).
    x_d = (uv[:, 0] - cam.cx) / cam.fx
    y_d = (uv[:, 1] - cam.cy) / cam.fy
    theta_d = np.hypot(x_d, y_d)
    assert np.all(finite[theta_d < 1.5])
    err = np.linalg.norm(cam.rays_to_pixels(rays[finite]) - uv[finite], axis=1)
    assert err.max() < ROUND_TRIP_TOL_PX


def test_fisheye_pixels_beyond_90_degrees_get_nan_rays() -> None:
    corner = np.array([[-0.5, -0.5], [511.5, 511.5]])  # theta_d ~ 1.9 rad
    assert np.all(np.isnan(TUMVI_FISHEYE.pixels_to_rays(corner)[:, :2]))
    rays = TUMVI_FISHEYE.pixels_to_rays(_grid_over_image(TUMVI_FISHEYE))
    assert 0.05 < np.mean(np.isnan(rays[:, 0])) < 0.2  # the corners outside the 90-deg circle


@pytest.mark.parametrize("cam", [TUMVI_FISHEYE, NARROW_EQUIDISTANT], ids=["tumvi", "narrow"])
def test_equidistant_projection_agrees_with_opencv_fisheye(cam: PinholeCamera, rng) -> None:
    n = 500
    points = np.column_stack([rng.uniform(-2.0, 2.0, n), rng.uniform(-2.0, 2.0, n),
                              np.ones(n)]) * rng.uniform(0.5, 50.0, (n, 1))
    points = np.vstack([points, [[0.0, 0.0, 3.0]]])  # the optical axis: r = 0
    expected, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                            cam.K, cam.dist_coeffs)
    np.testing.assert_allclose(cam.rays_to_pixels(points), expected.reshape(-1, 2), rtol=0,
                               atol=OPENCV_AGREEMENT_TOL_PX)
    assert np.all(np.isnan(cam.rays_to_pixels(np.array([[0.1, 0.2, -1.0]]))))


def test_equidistant_is_not_radtan_with_the_same_numbers() -> None:
    # Guards the tests above against a model switch that is ignored.
    radtan = PinholeCamera(*[getattr(NARROW_EQUIDISTANT, k) for k in
                             ("width", "height", "fx", "fy", "cx", "cy", "distortion")])
    assert radtan.model is DistortionModel.RADTAN
    ray = np.array([[0.5, 0.3, 1.0]])
    assert np.linalg.norm(radtan.rays_to_pixels(ray) - NARROW_EQUIDISTANT.rays_to_pixels(ray)) > 10


@pytest.mark.parametrize("kwargs", [
    dict(distortion=(0.1, 0.0, 0.0, 0.0, 0.0), distortion_model="equidistant"),
    dict(distortion=(), distortion_model="equidistant"),
    dict(distortion=(0.1, 0.0, 0.0, 0.0), distortion_model="none"),
    dict(distortion=(), distortion_model="radtan"),
    dict(distortion=(0.1, 0.0, 0.0, 0.0), distortion_model="fisheye"),
])
def test_model_and_coefficients_must_agree(kwargs) -> None:
    with pytest.raises(ValueError):
        PinholeCamera(400, 300, 300.0, 300.0, 199.5, 149.5, **kwargs)


def test_the_model_defaults_from_the_coefficients() -> None:
    assert PinholeCamera(4, 3, 3.0, 3.0, 1.5, 1.0).model is DistortionModel.NONE
    assert EUROC_CAM0.model is DistortionModel.RADTAN
    assert NARROW_EQUIDISTANT == PinholeCamera(400, 300, 346.4, 345.0, 201.3, 148.9,
                                               (0.02, -0.004, 0.0, 0.0),
                                               DistortionModel.EQUIDISTANT)
