"""The terrain renderer: geometry, world-fixed texture, shading, sensor, truth, images in logs."""

from __future__ import annotations

import math
import sys
import types

import cv2
import numpy as np
import pytest

from cdtm_graph.camera import DOWNWARD_BODY_T_CAM, PinholeCamera
from cdtm_graph.cli import main
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import SimulationError
from cdtm_graph.flightlog import read_flightlog
from cdtm_graph.geometry import make_pose
from cdtm_graph.sim.render import (
    OrthophotoTexture,
    ProceduralTexture,
    Renderer,
    RenderSettings,
    motion_blur_kernel,
    true_correspondences,
)

ALTITUDE_M = 1000.0
#: Float round-off of ray directions and hit points, relative.
EXACT_RTOL = 1e-9


@pytest.fixture(scope="module")
def coarse_texture(seed: int) -> ProceduralTexture:
    """Textures whose octaves are all far coarser than the ground pixel (<= 20 m in these
    small images) are never faded: every pixel samples the same function, so renders
    compare exactly."""
    return ProceduralTexture(seed=seed, longest_wavelength_m=3200.0,
                             shortest_wavelength_m=200.0)


def _flat(height_m: float = 0.0, size_m: float = 6000.0, spacing_m: float = 50.0) -> Dtm:
    n = int(size_m / spacing_m) + 1
    return Dtm(np.full((n, n), height_m), -size_m / 2, -size_m / 2, spacing_m, spacing_m)


def _nadir(x: float = 0.0, y: float = 0.0, z: float = ALTITUDE_M) -> np.ndarray:
    """world_T_cam of a level downward camera (cam x = east, cam y = south)."""
    return make_pose(DOWNWARD_BODY_T_CAM[:3, :3], np.array([x, y, z]))


def test_flat_ground_radiance_is_albedo_times_lambert_at_the_analytic_hit_points(coarse_texture):
    camera = PinholeCamera.from_fov(64, 48, 60.0)
    settings = RenderSettings(sun_elevation_deg=30.0, ambient=0.2)
    renderer = Renderer(_flat(), camera, coarse_texture, settings)
    radiance = renderer.radiance(_nadir(10.0, -20.0))
    v, u = np.mgrid[0:48, 0:64]
    x = 10.0 + ALTITUDE_M * (u - camera.cx) / camera.fx
    y = -20.0 - ALTITUDE_M * (v - camera.cy) / camera.fy  # cam y points south
    albedo = coarse_texture.albedo(x.ravel(), y.ravel(), np.ones(x.size)).reshape(x.shape)
    shade = 0.2 + 0.8 * math.sin(math.radians(30.0))
    np.testing.assert_allclose(radiance, albedo * shade, rtol=1e-7)


def test_texture_is_fixed_on_the_ground(coarse_texture):
    """Moving the camera by five ground pixels shifts the image by five pixels, exactly."""
    camera = PinholeCamera.from_fov(80, 60, 60.0)
    renderer = Renderer(_flat(), camera, coarse_texture)
    step_m = 5 * ALTITUDE_M / camera.fx
    a = renderer.radiance(_nadir(0.0))
    b = renderer.radiance(_nadir(step_m))
    np.testing.assert_allclose(b[:, :-5], a[:, 5:], rtol=EXACT_RTOL)
    assert np.std(a) > 0.05  # there is a texture to compare


@pytest.mark.parametrize("sun_azimuth_deg, lit", [(90.0, False), (270.0, True)])
def test_lambertian_shading_of_a_slope(sun_azimuth_deg, lit):
    """A plane rising toward the east (30 deg): lit from the west it faces the sun, from
    the east at 20 deg elevation it turns away from it (ambient only)."""
    slope = math.tan(math.radians(30.0))
    xs = np.arange(-3000.0, 3001.0, 50.0)
    dtm = Dtm(np.tile(slope * xs, (xs.size, 1)), -3000.0, -3000.0, 50.0, 50.0)
    flat_albedo = ProceduralTexture(contrast=0.0, mean_albedo=0.5)
    settings = RenderSettings(sun_azimuth_deg=sun_azimuth_deg, sun_elevation_deg=20.0,
                              ambient=0.25)
    radiance = Renderer(dtm, PinholeCamera.from_fov(16, 12, 40.0), flat_albedo,
                        settings).radiance(_nadir(z=3000.0))
    normal = np.array([-slope, 0.0, 1.0]) / math.hypot(slope, 1.0)
    cos_sun = float(normal @ settings.sun_world)
    assert (cos_sun > 0) == lit
    expected = 0.5 * (0.25 + 0.75 * max(cos_sun, 0.0))
    np.testing.assert_allclose(radiance, expected, rtol=EXACT_RTOL)


def test_texture_detail_finer_than_the_pixels_fades_out(seed, rng):
    texture = ProceduralTexture(seed=seed)
    x, y = rng.uniform(-5e4, 5e4, (2, 20000))
    fine = texture.albedo(x, y, np.full(x.size, 0.01))
    assert abs(np.std(fine) - texture.contrast) < 0.1 * texture.contrast
    # A footprint beyond the longest wavelength / FADE_START: every octave is cut.
    flat = texture.albedo(x, y, np.full(x.size, texture.longest_wavelength_m))
    np.testing.assert_array_equal(flat, texture.mean_albedo)


@pytest.mark.slow
def test_orthophoto_texture_samples_its_grid_and_averages_when_far():
    rows, cols = 64, 96
    ramp = 0.2 + 0.005 * np.arange(cols)[None, :] + 0.002 * np.arange(rows)[:, None]
    ortho = OrthophotoTexture(ramp, x0=100.0, y0=500.0, dx=2.0, dy=-2.0)
    c, r = np.array([3.0, 40.5, 70.25]), np.array([5.0, 20.0, 33.5])
    x, y = 100.0 + 2.0 * c, 500.0 - 2.0 * r
    np.testing.assert_allclose(ortho.albedo(x, y, np.full(3, 0.1)),
                               0.2 + 0.005 * c + 0.002 * r, rtol=1e-6)
    # Far away a checkerboard of single pixels is its mean grey, not aliased black/white.
    checker = (np.indices((rows, cols)).sum(axis=0) % 2).astype(float)
    board = OrthophotoTexture(checker, 0.0, 0.0, 1.0, 1.0)
    far = board.albedo(np.array([40.3, 50.7]), np.array([30.1, 20.6]), np.full(2, 8.0))
    np.testing.assert_allclose(far, 0.5, atol=0.02)
    assert np.isnan(ortho.albedo(np.array([0.0]), np.array([0.0]), np.ones(1)))[0]


class _FakeRasterio:
    """What OrthophotoTexture.from_geotiff uses of rasterio."""

    def __init__(self, transform, bands, crs=None):
        self.transform, self.crs, self.count = transform, crs, bands.shape[0]
        self._bands = bands

    def open(self, path):
        return self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def read(self, masked=False):
        return np.ma.masked_array(self._bands)


def test_orthophoto_geotiff_grid_and_origin(tmp_path, monkeypatch):
    rgb = np.zeros((3, 4, 5), np.uint8)
    rgb[1, 2, 3] = 255  # one green pixel
    fake = _FakeRasterio((2.0, 0.0, 1000.0, 0.0, -2.0, 5000.0), rgb)
    monkeypatch.setitem(sys.modules, "rasterio", types.SimpleNamespace(open=fake.open))
    ortho = OrthophotoTexture.from_geotiff(tmp_path / "o.tif", origin_enu_m=(1000.0, 4000.0, 0.0))
    # pixel (row 2, col 3) centre: x = 1000 + 2 * 3.5 - 1000, y = 5000 - 2 * 2.5 - 4000
    assert ortho.albedo(np.array([7.0]), np.array([995.0]), np.array([0.1]))[0] == \
        pytest.approx(0.587, abs=1e-6)
    fake.crs = types.SimpleNamespace(is_geographic=True)
    with pytest.raises(SimulationError, match="geographic"):
        OrthophotoTexture.from_geotiff(tmp_path / "o.tif")
    monkeypatch.setitem(sys.modules, "rasterio", None)
    with pytest.raises(SimulationError, match="rasterio"):
        OrthophotoTexture.from_geotiff(tmp_path / "o.tif")


def test_sensor_gain_noise_and_blur(seed, rng):
    camera = PinholeCamera.from_fov(120, 90, 60.0)
    renderer = Renderer(_flat(), camera, ProceduralTexture(seed=seed),
                        RenderSettings(noise_sigma_dn=3.0))
    pose = _nadir()
    radiance = renderer.radiance(pose)
    np.testing.assert_array_equal(renderer.render(pose, gain=1.1),
                                  np.clip(np.rint(radiance * 255 * 1.1), 0, 255))
    noisy = renderer.render(pose, rng=rng).astype(float)
    residual = noisy - np.clip(np.rint(radiance * 255), 0, 255)
    assert abs(np.std(residual) - 3.0) < 0.2
    blurred = renderer.render(pose, blur_px=(4.0, 0.0)).astype(float)
    sharp = renderer.render(pose).astype(float)
    # A blur along u smooths the image along u much more than along v.
    smoothing_u = np.abs(np.diff(blurred, axis=1)).mean() / np.abs(np.diff(sharp, axis=1)).mean()
    smoothing_v = np.abs(np.diff(blurred, axis=0)).mean() / np.abs(np.diff(sharp, axis=0)).mean()
    assert smoothing_u < smoothing_v - 0.2


@pytest.mark.parametrize("du, dv", [(1.0, 0.0), (2.5, 1.5), (0.0, 7.0)])
def test_motion_blur_kernel_is_a_centred_segment(du, dv):
    kernel = motion_blur_kernel(du, dv)
    assert kernel.sum() == pytest.approx(1.0)
    half = kernel.shape[0] // 2
    v, u = np.mgrid[-half:half + 1, -half:half + 1]
    assert (kernel * u).sum() == pytest.approx(0.0, abs=1e-9)
    assert (kernel * v).sum() == pytest.approx(0.0, abs=1e-9)
    length = math.hypot(du, dv)
    along = (u * du + v * dv) / length
    across = (-u * dv + v * du) / length
    # a uniform segment of length L has variance L^2 / 12; splatting adds < 1/4 px^2
    assert abs((kernel * along ** 2).sum() - length ** 2 / 12) < 0.25
    assert (kernel * across ** 2).sum() < 0.25


@pytest.mark.parametrize("model, coeffs", [("radtan", (-0.2, 0.05, 0.001, -0.001)),
                                           ("equidistant", (0.01, -0.002, 0.0, 0.0))])
def test_lens_distortion_is_the_camera_models(coarse_texture, model, coeffs):
    """A distorted camera sees at pixel p what an undistorted one sees along p's ray."""
    plain = PinholeCamera.from_fov(80, 60, 60.0)
    distorted = PinholeCamera(80, 60, plain.fx, plain.fy, plain.cx, plain.cy, coeffs, model)
    terrain = _flat()
    pose = _nadir()
    warped = Renderer(terrain, distorted, coarse_texture).radiance(pose)
    v, u = np.mgrid[0:60, 0:80]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    # The same ground points, through the undistorted model.
    uv_plain = plain.rays_to_pixels(distorted.pixels_to_rays(uv))
    x = ALTITUDE_M * (uv_plain[:, 0] - plain.cx) / plain.fx
    y = -ALTITUDE_M * (uv_plain[:, 1] - plain.cy) / plain.fy
    expected = coarse_texture.albedo(x, y, np.ones(x.size)) * (
        0.3 + 0.7 * math.sin(math.radians(45.0)))
    np.testing.assert_allclose(warped.ravel(), expected, rtol=1e-7)
    assert np.abs(uv_plain - uv).max() > 3.0  # the lens moves pixels by several pixels


def _looking_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_T_cam of a camera at ``position`` whose optical axis points at ``target``."""
    z = (target - position) / np.linalg.norm(target - position)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_pose(np.column_stack([x, np.cross(z, x), z]), position)


def test_true_correspondences_respect_occlusion():
    """A 400 m ridge hides from a low camera b the ground a high camera a sees behind it."""
    xs = np.arange(-2000.0, 2001.0, 10.0)
    ridge = np.where((xs >= 100.0) & (xs <= 120.0), 400.0, 0.0)
    terrain = Dtm(np.tile(ridge, (xs.size, 1)), -2000.0, -2000.0, 10.0, 10.0)
    camera = PinholeCamera.from_fov(200, 200, 90.0)
    a = _nadir(300.0, 0.0, 1000.0)
    b = _looking_at(np.array([-200.0, 0.0, 450.0]), np.array([150.0, 0.0, 0.0]))
    ground = np.array([[300.0, 0.0, 0.0], [-50.0, 0.0, 0.0]])  # behind / before the ridge
    uv_a = camera.rays_to_pixels((ground - a[:3, 3]) @ a[:3, :3])
    uv_b, seen = true_correspondences(terrain, camera, a, b, uv_a)
    expected_b = camera.rays_to_pixels((ground - b[:3, 3]) @ b[:3, :3])
    assert camera.in_image(expected_b).all()  # both would be in b's image ...
    assert not seen[0] and np.isnan(uv_b[0]).all()  # ... but the ridge hides the first
    assert seen[1]
    np.testing.assert_allclose(uv_b[1], expected_b[1], atol=1e-6)


def test_render_settings_reject_bad_values():
    for bad in ({"exposure_jitter": 1.5}, {"sun_elevation_deg": 0.0}, {"ambient": -0.1},
                {"noise_sigma_dn": float("nan")}):
        with pytest.raises(SimulationError):
            RenderSettings(**bad)


def test_simulate_with_images_writes_them_and_lists_them(tmp_path, capsys):
    out = tmp_path / "log"
    assert main(["simulate", str(out), "--images", "--frames", "3", "--resolution", "96",
                 "72", "--features", "20", "--exposure-jitter", "0.1"]) == 0
    flight = read_flightlog(out)
    assert flight.frames.image == ("images/000000.png", "images/000001.png",
                                   "images/000002.png")
    images = [cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED) for name in flight.frames.image]
    assert all(im.shape == (72, 96) and im.dtype == np.uint8 for im in images)
    assert np.std(images[0]) > 10  # textured
    assert flight.tracks is not None  # the ideal ray-cast tracks are still written
    assert "rendered 3 images" in capsys.readouterr().out
