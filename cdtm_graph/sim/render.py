"""What a downward camera sees: terrain ray cast exactly, a world-fixed ground texture, shading.

The renderer is the visual front-end's test bench: images of a flight whose every pixel
is known, so a tracker's output can be compared with the truth
(:func:`true_correspondences`). Per pixel:

* **Geometry.** The ray of the pixel centre (through the camera model, so lens
  distortion is the model's own: :meth:`~cdtm_graph.camera.PinholeCamera.pixels_to_rays`)
  is cast into the *true* terrain with :meth:`~cdtm_graph.dtm.Dtm.raycast`: exact first
  hit on the bilinear surface, so hills hide what lies behind them.
* **Ground texture** fixed in world coordinates, sampled at the hit's (x, y): procedural
  multi-scale gradient noise by default (:class:`ProceduralTexture`), or an orthophoto
  (:class:`OrthophotoTexture`, e.g. a GeoTIFF). Both are *band-limited to the pixel
  footprint* (octaves, or mipmap levels, finer than ~1.5 ground pixels fade out): a
  point-sampled texture finer than the pixels would alias into patterns that move with
  the camera instead of the ground, and no tracker could follow them.
* **Shading.** Lambertian: ``albedo * (ambient + (1 - ambient) * max(0, n . sun))`` with
  ``n`` the terrain's normal at the hit (cast shadows are not modelled).
* **Sensor.** An exposure gain per frame (optionally jittered), an optional linear
  motion blur along the image motion, Gaussian read noise, 8-bit quantization. Rays that
  miss the terrain see black.

Pixels follow OpenCV: ``(0, 0)`` is the centre of the top-left pixel (docs/flightlog.md,
"Frames, units and conventions").
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import cv2
import numpy as np
from numba import prange

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.dtm import Dtm, visible_from
from cdtm_graph.errors import SimulationError
from cdtm_graph.sim.settings import RenderSettings
from factors.jit import njit

if TYPE_CHECKING:
    from cdtm_graph.sim.simulate import SimulationResult

logger = logging.getLogger(__name__)

__all__ = [
    "GroundTexture",
    "OrthophotoTexture",
    "ProceduralTexture",
    "RenderSettings",
    "RenderedFlight",
    "Renderer",
    "render_flight",
    "true_correspondences",
    "write_images",
]

#: A texture detail fades in between these multiples of the ground footprint of a pixel:
#: absent below the first (it would alias), full above the second.
FADE_START_PX = 1.5
FADE_END_PX = 3.0

#: Grazing hits stretch the footprint by 1/cos(incidence); the stretch is capped here
#: (the renderer draws no horizon, this only guards the division).
MIN_INCIDENCE_COS = 0.2

#: A ground point counts as seen by the second camera if the first terrain hit toward it
#: lies within this distance of it (m): far above round-off, far below any terrain detail.
TRUTH_OCCLUSION_TOLERANCE_M = 0.01

#: Largest image side the renderer accepts (pixels): a typo guard, 16k x 16k is 2 GB of rays.
MAX_IMAGE_SIDE_PX = 16384


class GroundTexture(Protocol):
    """An albedo field on the ground, fixed in world coordinates."""

    def albedo(self, x_m: np.ndarray, y_m: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        """Albedo in [0, 1] at world points, band-limited to each point's footprint.

        Args:
            x_m, y_m: (N,) world coordinates (m).
            footprint_m: (N,) ground size of the pixel that samples each point (m).

        Returns:
            (N,) albedo; NaN where the texture has no data.
        """
        ...


@dataclass(frozen=True)
class ProceduralTexture:
    """Multi-scale gradient (Perlin) noise in world coordinates, band-limited per pixel.

    Octaves have wavelengths from ``longest_wavelength_m`` down to ``shortest_wavelength_m``,
    halving each time, amplitudes ``(wavelength / longest) ** hurst`` (a fractal ground:
    fields at the long scales, texture at the short ones); each octave is rotated and
    shifted by its own pseudo-random amount so no lattice direction dominates. The
    albedo is ``mean_albedo + contrast * s`` clipped to [0.02, 0.98], ``s`` the octave sum
    normalized to unit standard deviation when all octaves are present.

    Attributes:
        seed: selects the pattern (any integer >= 0).
        longest_wavelength_m, shortest_wavelength_m: the octave range (m).
        hurst: spectral slope: 0 = every octave equally strong, 1 = smooth.
        mean_albedo: mean albedo.
        contrast: standard deviation of the albedo (all octaves present).
    """

    seed: int = 0
    longest_wavelength_m: float = 400.0
    shortest_wavelength_m: float = 0.5
    hurst: float = 0.3
    mean_albedo: float = 0.45
    contrast: float = 0.18

    def __post_init__(self) -> None:
        if not (isinstance(self.seed, int | np.integer) and self.seed >= 0):
            raise SimulationError(f"texture seed = {self.seed!r}, expected an integer >= 0")
        if not (0 < self.shortest_wavelength_m < self.longest_wavelength_m < math.inf):
            raise SimulationError(
                f"texture wavelengths {self.shortest_wavelength_m!r}..."
                f"{self.longest_wavelength_m!r} m, expected 0 < shortest < longest")
        for name in ("hurst", "mean_albedo", "contrast"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise SimulationError(f"texture {name} = {value!r}, expected a finite value >= 0")

    def _octaves(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = int(math.floor(math.log2(self.longest_wavelength_m / self.shortest_wavelength_m))) + 1
        wavelength = self.longest_wavelength_m / 2.0 ** np.arange(n)
        amplitude = (wavelength / self.longest_wavelength_m) ** self.hurst
        # Perlin noise of unit lattice has a standard deviation of about 0.22 per octave.
        amplitude = amplitude / (PERLIN_STD * math.sqrt(float(np.sum(amplitude ** 2))))
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x7E47]))
        # rotation (cos, sin) and offset of each octave's lattice
        angle = rng.uniform(0.0, 2.0 * math.pi, n)
        frame = np.column_stack([np.cos(angle), np.sin(angle), rng.uniform(0.0, 256.0, (n, 2))])
        return wavelength, amplitude, frame

    def albedo(self, x_m: np.ndarray, y_m: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        wavelength, amplitude, frame = self._octaves()
        x = np.ascontiguousarray(x_m, dtype=np.float64).ravel()
        y = np.ascontiguousarray(y_m, dtype=np.float64).ravel()
        fp = np.ascontiguousarray(footprint_m, dtype=np.float64).ravel()
        s = np.empty_like(x)
        _noise_octaves(x, y, fp, wavelength, amplitude, frame, np.uint64(self.seed & 0xFFFFFFFF),
                       FADE_START_PX, FADE_END_PX, s)
        out = np.clip(self.mean_albedo + self.contrast * s, 0.02, 0.98)
        out[~np.isfinite(s)] = np.nan
        return out


#: Standard deviation of 2-D Perlin noise (this implementation) over the plane.
PERLIN_STD = 0.22


_MASK32 = np.uint64(0xFFFFFFFF)


@njit(cache=True, inline="always")
def _hash(ix: np.int64, iy: np.int64, seed: np.uint64) -> np.uint64:
    """32-bit integer hash of a lattice corner (numba widens integer products to 64 bits,
    so every step is masked back to 32)."""
    h = ((np.uint64(ix) & _MASK32) * np.uint64(0x8DA6B343)
         ^ (np.uint64(iy) & _MASK32) * np.uint64(0xD8163841)
         ^ seed * np.uint64(0xCB1AB31F)) & _MASK32
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x2C1B3C6D)) & _MASK32
    h ^= h >> np.uint64(12)
    h = (h * np.uint64(0x297A2D39)) & _MASK32
    h ^= h >> np.uint64(15)
    return h


#: Perlin's gradients: 16 unit vectors evenly spread (a table, not trigonometry per corner).
_GRADIENTS = np.array([[math.cos(a), math.sin(a)] for a in np.arange(16) * (2 * math.pi / 16)])


@njit(cache=True, inline="always")
def _grad(ix: np.int64, iy: np.int64, seed: np.uint64, fx: float, fy: float) -> float:
    g = _GRADIENTS[np.int64(_hash(ix, iy, seed) >> np.uint64(28))]
    return g[0] * fx + g[1] * fy


@njit(cache=True, inline="always")
def _perlin(x: float, y: float, seed: np.uint64) -> float:
    x0 = math.floor(x)
    y0 = math.floor(y)
    fx = x - x0
    fy = y - y0
    ix = np.int64(x0)
    iy = np.int64(y0)
    u = fx * fx * fx * (fx * (fx * 6.0 - 15.0) + 10.0)
    v = fy * fy * fy * (fy * (fy * 6.0 - 15.0) + 10.0)
    n00 = _grad(ix, iy, seed, fx, fy)
    n10 = _grad(ix + 1, iy, seed, fx - 1.0, fy)
    n01 = _grad(ix, iy + 1, seed, fx, fy - 1.0)
    n11 = _grad(ix + 1, iy + 1, seed, fx - 1.0, fy - 1.0)
    a = n00 + u * (n10 - n00)
    b = n01 + u * (n11 - n01)
    return a + v * (b - a)


@njit(cache=True, parallel=True)
def _noise_octaves(x, y, footprint, wavelength, amplitude, frame, seed, fade_start, fade_end,
                   out):
    n_oct = wavelength.shape[0]
    for i in prange(x.shape[0]):
        if not (math.isfinite(x[i]) and math.isfinite(y[i])):
            out[i] = np.nan
            continue
        s = 0.0
        for o in range(n_oct):
            # fade: 0 where the wavelength spans fade_start pixels, 1 from fade_end pixels
            w = (wavelength[o] / footprint[i] - fade_start) / (fade_end - fade_start)
            if w <= 0.0:
                break  # octaves get finer: the rest are cut too
            if w > 1.0:
                w = 1.0
            c, sn = frame[o, 0], frame[o, 1]
            xs = (c * x[i] - sn * y[i]) / wavelength[o] + frame[o, 2]
            ys = (sn * x[i] + c * y[i]) / wavelength[o] + frame[o, 3]
            s += w * amplitude[o] * _perlin(xs, ys, seed + np.uint64(o))
        out[i] = s


class OrthophotoTexture:
    """An orthophoto (albedo raster) in world coordinates, sampled from a mipmap.

    The grid follows the DTM convention: ``image[r, c]`` is the albedo at
    ``x = x0 + c*dx``, ``y = y0 + r*dy`` (``dy < 0`` for north-up rasters). A sample is
    trilinear: bilinear in the two mipmap levels around the pixel footprint, blended.

    Args:
        image: (rows, cols) albedo in [0, 1] (NaN: no data).
        x0, y0: world position of ``image[0, 0]`` (m).
        dx, dy: spacing (m), nonzero.
    """

    def __init__(self, image: np.ndarray, x0: float, y0: float, dx: float, dy: float):
        img = np.asarray(image, dtype=np.float32)
        if img.ndim != 2 or min(img.shape) < 2:
            raise SimulationError(f"orthophoto of shape {img.shape}, expected a 2-D raster of "
                                  "at least 2x2 pixels")
        if not all(math.isfinite(v) for v in (x0, y0, dx, dy)) or dx == 0 or dy == 0:
            raise SimulationError(f"orthophoto grid x0={x0}, y0={y0}, dx={dx}, dy={dy}, "
                                  "expected finite numbers and nonzero spacings")
        self.x0, self.y0, self.dx, self.dy = float(x0), float(y0), float(dx), float(dy)
        self.shape = img.shape
        # Mipmap: level l has spacing 2^l; pyrDown low-passes before decimating.
        levels: list[np.ndarray] = [np.nan_to_num(img, nan=0.0)]
        while min(levels[-1].shape) >= 4:
            levels.append(cv2.pyrDown(levels[-1]))
        self._levels = levels
        self._flat = np.concatenate([lv.ravel() for lv in levels]).astype(np.float32)
        self._offsets = np.cumsum([0] + [lv.size for lv in levels[:-1]]).astype(np.int64)
        self._shapes = np.array([lv.shape for lv in levels], dtype=np.int64)
        self._valid = np.isfinite(img)

    @classmethod
    def from_geotiff(cls, path: str | os.PathLike,
                     origin_enu_m: Sequence[float] = (0.0, 0.0, 0.0)) -> OrthophotoTexture:
        """Read an orthophoto GeoTIFF (1 band gray, or RGB: its luma) with rasterio.

        The raster must be in the same metric projected CRS as the DTM; ``origin_enu_m``
        (as in flight.yaml's ``dtm.origin_enu_m``) is subtracted to give world x, y.
        8-bit values are scaled by 1/255, 16-bit by 1/65535, floats are taken as albedo.

        Raises:
            SimulationError: rasterio is missing, the file is unreadable, geographic,
                rotated, or has no band.
        """
        try:
            import rasterio
        except ImportError:
            raise SimulationError(
                f"{path}: reading a GeoTIFF orthophoto needs rasterio, expected it installed: "
                "pip install 'cdtm-graph[geotiff]'") from None
        try:
            with rasterio.open(path) as src:
                transform, crs, count = src.transform, src.crs, src.count
                bands = src.read(masked=True)
        except Exception as exc:  # rasterio has its own error types; report them alike
            raise SimulationError(f"{path}: cannot read the orthophoto ({exc}), "
                                  "expected a readable GeoTIFF") from None
        if count < 1:
            raise SimulationError(f"{path}: has no raster band, expected 1 (gray) or 3+ (RGB)")
        if crs is not None and getattr(crs, "is_geographic", False):
            raise SimulationError(f"{path}: CRS {crs} is geographic (degrees), expected the "
                                  "DTM's metric projected CRS")
        a, b, c, d, e, f = (float(transform[k]) for k in range(6))
        if b != 0.0 or d != 0.0:
            raise SimulationError(f"{path}: affine transform is rotated or sheared "
                                  f"(b={b}, d={d}), expected a north-up grid")
        data = np.ma.asarray(bands)
        dtype = data.dtype
        values = np.ma.filled(data.astype(np.float64), np.nan)
        if dtype == np.uint8:
            values /= 255.0
        elif dtype == np.uint16:
            values /= 65535.0
        # ITU-R BT.601 luma of RGB; a gray raster is its own.
        gray = (values[0] if values.shape[0] < 3
                else 0.299 * values[0] + 0.587 * values[1] + 0.114 * values[2])
        ox, oy = float(origin_enu_m[0]), float(origin_enu_m[1])
        return cls(gray, c + 0.5 * a - ox, f + 0.5 * e - oy, a, e)

    def albedo(self, x_m: np.ndarray, y_m: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x_m, dtype=np.float64).ravel()
        y = np.ascontiguousarray(y_m, dtype=np.float64).ravel()
        fp = np.ascontiguousarray(footprint_m, dtype=np.float64).ravel()
        col = (x - self.x0) / self.dx
        row = (y - self.y0) / self.dy
        # Standard mipmapping: the level whose texel spans the footprint (its finest
        # detail, two texels, is then as long as the procedural texture's faded octaves).
        spacing = min(abs(self.dx), abs(self.dy))
        level = np.log2(np.maximum(fp / spacing, 1.0))
        out = np.empty_like(x)
        _trilinear(self._flat, self._offsets, self._shapes, row, col, level, out)
        rows, cols = self.shape
        inside = (row >= 0) & (row <= rows - 1) & (col >= 0) & (col <= cols - 1)
        valid = np.zeros_like(inside)
        r = np.clip(np.rint(row[inside]).astype(np.int64), 0, rows - 1)
        c = np.clip(np.rint(col[inside]).astype(np.int64), 0, cols - 1)
        valid[inside] = self._valid[r, c]
        out[~valid] = np.nan
        return out


@njit(cache=True, inline="always")
def _bilinear_level(flat, offset, rows, cols, r, c):
    r = min(max(r, 0.0), rows - 1.0)
    c = min(max(c, 0.0), cols - 1.0)
    i = min(int(r), rows - 2) if rows > 1 else 0
    j = min(int(c), cols - 2) if cols > 1 else 0
    a = c - j
    b = r - i
    base = offset + i * cols + j
    v00 = flat[base]
    v01 = flat[base + 1] if cols > 1 else v00
    v10 = flat[base + cols] if rows > 1 else v00
    v11 = flat[base + cols + 1] if (rows > 1 and cols > 1) else v00
    return (v00 * (1 - a) + v01 * a) * (1 - b) + (v10 * (1 - a) + v11 * a) * b


@njit(cache=True, parallel=True)
def _trilinear(flat, offsets, shapes, row, col, level, out):
    n_levels = offsets.shape[0]
    for i in prange(row.shape[0]):
        lv = min(level[i], n_levels - 1.0)
        l0 = int(lv)
        l1 = min(l0 + 1, n_levels - 1)
        w = lv - l0
        s0 = 0.5 ** l0
        s1 = 0.5 ** l1
        # cv2.pyrDown centres level sample k on fine-grid sample 2^l k
        v0 = _bilinear_level(flat, offsets[l0], shapes[l0, 0], shapes[l0, 1], row[i] * s0,
                             col[i] * s0)
        v1 = _bilinear_level(flat, offsets[l1], shapes[l1, 0], shapes[l1, 1], row[i] * s1,
                             col[i] * s1)
        out[i] = v0 * (1 - w) + v1 * w


class Renderer:
    """Renders a camera's view of a terrain; the pixel rays are computed once.

    Args:
        terrain: the surface seen (the *true* terrain of a simulation).
        camera: the camera model (any object with ``width``, ``height``, ``fx``, ``fy``
            and ``pixels_to_rays``; distortion is the model's).
        texture: the ground albedo; a :class:`ProceduralTexture` by default.
        settings: light and sensor.
    """

    def __init__(self, terrain: Dtm, camera: PinholeCamera, texture: GroundTexture | None = None,
                 settings: RenderSettings | None = None):
        if max(camera.width, camera.height) > MAX_IMAGE_SIDE_PX:
            raise SimulationError(f"image {camera.width}x{camera.height}, expected sides of at "
                                  f"most {MAX_IMAGE_SIDE_PX} pixels")
        self.terrain = terrain
        self.camera = camera
        self.texture: GroundTexture = texture if texture is not None else ProceduralTexture()
        self.settings = settings or RenderSettings()
        v, u = np.mgrid[0:camera.height, 0:camera.width]
        rays = camera.pixels_to_rays(np.column_stack([u.ravel(), v.ravel()]).astype(float))
        self._valid_ray = np.isfinite(rays).all(axis=1)
        rays[~self._valid_ray] = (0.0, 0.0, 1.0)  # cast, then blanked
        self._rays_cam = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        # Size of a pixel across the ray per metre of range: a pinhole pixel off the axis
        # by theta subtends cos(theta)^2 / f radially and cos(theta) / f tangentially;
        # the larger (distortion ignored: it only sets where texture detail fades).
        focal_px = math.sqrt(camera.fx * camera.fy)
        self._footprint_per_m = self._rays_cam[:, 2] / focal_px

    def radiance(self, world_T_cam: np.ndarray) -> np.ndarray:
        """Noise-free image in units of full scale (1.0 = 255 DN at exposure 1).

        Args:
            world_T_cam: (4, 4) camera pose.

        Returns:
            (height, width) float64 radiance; 0 where the ray misses the terrain.
        """
        R, p = world_T_cam[:3, :3], world_T_cam[:3, 3]
        directions = self._rays_cam @ R.T
        hits = self.terrain.raycast(p, directions)
        hit = hits.hit & self._valid_ray
        n = hits.normal[hit]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        d = directions[hit]  # unit: hits.t is the range in metres
        cos_incidence = np.maximum(np.abs(np.einsum("ij,ij->i", n, d)), MIN_INCIDENCE_COS)
        footprint = hits.t[hit] * self._footprint_per_m[hit] / cos_incidence
        albedo = self.texture.albedo(hits.point[hit, 0], hits.point[hit, 1], footprint)
        s = self.settings
        shade = s.ambient + (1.0 - s.ambient) * np.maximum(n @ s.sun_world, 0.0)
        out = np.zeros(self.camera.width * self.camera.height)
        out[hit] = np.nan_to_num(albedo * shade, nan=0.0)
        return out.reshape(self.camera.height, self.camera.width)

    def render(self, world_T_cam: np.ndarray, gain: float = 1.0,
               blur_px: tuple[float, float] = (0.0, 0.0),
               rng: np.random.Generator | None = None) -> np.ndarray:
        """One 8-bit grayscale image.

        Args:
            world_T_cam: (4, 4) camera pose.
            gain: this frame's exposure relative to ``settings.exposure``.
            blur_px: (du, dv) image motion during the exposure (px): a linear blur along it.
            rng: sensor noise source (None: no noise).

        Returns:
            (height, width) uint8 image.
        """
        image: np.ndarray = self.radiance(world_T_cam) * (255.0 * self.settings.exposure * gain)
        if math.hypot(*blur_px) > 1e-3:
            image = cv2.filter2D(image, -1, motion_blur_kernel(*blur_px),
                                 borderType=cv2.BORDER_REPLICATE)
        if rng is not None and self.settings.noise_sigma_dn > 0:
            image = image + rng.normal(0.0, self.settings.noise_sigma_dn, image.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def motion_blur_kernel(du_px: float, dv_px: float, samples_per_px: int = 16) -> np.ndarray:
    """Normalized kernel of a uniform motion along (du, dv) pixels, centred (sub-pixel exact).

    Points along the segment are splatted bilinearly, so a 1.3 px blur differs from a
    1 px one.

    Returns:
        (k, k) float64 kernel summing to 1, k odd.
    """
    length = math.hypot(du_px, dv_px)
    half = int(math.ceil(length / 2)) + 1
    k = 2 * half + 1
    kernel = np.zeros((k, k))
    n = max(2, int(math.ceil(length * samples_per_px)) + 1)
    s = np.linspace(-0.5, 0.5, n)
    u, v = half + s * du_px, half + s * dv_px
    i0, j0 = np.floor(v).astype(int), np.floor(u).astype(int)
    a, b = u - j0, v - i0
    for di, dj, w in ((0, 0, (1 - a) * (1 - b)), (0, 1, a * (1 - b)),
                      (1, 0, (1 - a) * b), (1, 1, a * b)):
        np.add.at(kernel, (i0 + di, j0 + dj), w)
    return kernel / kernel.sum()


@dataclass(frozen=True)
class RenderedFlight:
    """The images of a simulated flight.

    Attributes:
        images: K (height, width) uint8 images, one per frame.
        gains: (K,) exposure gain of each frame (1 without jitter).
        blur_px: (K, 2) motion blur vector of each frame (px).
        seconds_per_frame: wall time of rendering, per frame.
    """

    images: list[np.ndarray]
    gains: np.ndarray
    blur_px: np.ndarray
    seconds_per_frame: float = field(default=float("nan"))


def _blur_vectors(camera: PinholeCamera, terrain: Dtm, world_T_cam: np.ndarray,
                  length_px: float) -> np.ndarray:
    """(K, 2) blur of ``length_px`` along each frame's image motion at the image centre."""
    k_frames = world_T_cam.shape[0]
    out = np.zeros((k_frames, 2))
    if length_px <= 0 or k_frames < 2:
        return out
    centre = np.array([[(camera.width - 1) / 2, (camera.height - 1) / 2]])
    ray = camera.pixels_to_rays(centre)[0]
    for k in range(k_frames):
        a, b = (k, k + 1) if k + 1 < k_frames else (k - 1, k)
        hit = terrain.raycast(world_T_cam[a][:3, 3], world_T_cam[a][:3, :3] @ ray)
        if not hit.hit[0]:
            continue
        to_point = hit.point[0] - world_T_cam[b][:3, 3]
        flow = camera.rays_to_pixels(to_point @ world_T_cam[b][:3, :3])[0] - centre[0]
        norm = float(np.linalg.norm(flow))
        if np.isfinite(norm) and norm > 0:
            out[k] = flow / norm * length_px
    return out


def render_flight(result: SimulationResult, settings: RenderSettings | None = None,
                  texture: GroundTexture | None = None,
                  progress: Callable[[int, int], None] | None = None) -> RenderedFlight:
    """Render every frame of a simulated flight from its true camera poses and terrain.

    Args:
        result: the simulation (``terrain`` is the truth the images show; the log's DTM
            is not used).
        settings: light and sensor; exposure jitter and noise are drawn from its seed.
        texture: the ground albedo (default :class:`ProceduralTexture` seeded by the
            settings' seed).
        progress: called with (frames done, total) after each frame.

    Returns:
        The images.
    """
    settings = settings or RenderSettings()
    camera = result.log.config.camera.camera
    if texture is None:
        texture = ProceduralTexture(seed=settings.seed)
    renderer = Renderer(result.terrain, camera, texture, settings)
    k_frames = result.world_T_cam.shape[0]
    rng_gain, rng_noise = (np.random.default_rng(s)
                           for s in np.random.SeedSequence([settings.seed, 0x1A6E]).spawn(2))
    gains = 1.0 + settings.exposure_jitter * np.asarray(rng_gain.uniform(-1.0, 1.0, k_frames))
    blur = _blur_vectors(camera, result.terrain, result.world_T_cam, settings.motion_blur_px)
    images = []
    start = time.perf_counter()
    for k in range(k_frames):
        images.append(renderer.render(result.world_T_cam[k], float(gains[k]), tuple(blur[k]),
                                      rng_noise))
        if progress is not None:
            progress(k + 1, k_frames)
    elapsed = (time.perf_counter() - start) / max(k_frames, 1)
    logger.info("rendered %d frames of %dx%d in %.3f s each", k_frames, camera.width,
                camera.height, elapsed)
    return RenderedFlight(images, gains, blur, elapsed)


#: Image files of a rendered flight, relative to the log directory.
IMAGE_DIR = "images"


def image_names(k_frames: int) -> tuple[str, ...]:
    """Relative paths of the frame images as frames.csv lists them."""
    return tuple(f"{IMAGE_DIR}/{k:06d}.png" for k in range(k_frames))


def write_images(images: Sequence[np.ndarray], log_dir: str | os.PathLike) -> tuple[str, ...]:
    """Write frame images as lossless PNG under ``log_dir/images``.

    Returns:
        Their paths relative to ``log_dir``, one per image.
    """
    root = Path(log_dir)
    names = image_names(len(images))
    (root / IMAGE_DIR).mkdir(parents=True, exist_ok=True)
    for name, image in zip(names, images, strict=True):
        if not cv2.imwrite(str(root / name), image):
            raise SimulationError(f"{root / name}: could not write the image")
    return names


def true_correspondences(terrain: Dtm, camera: PinholeCamera, world_T_cam_a: np.ndarray,
                         world_T_cam_b: np.ndarray, uv_a_px: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Where the ground seen at pixels of camera a appears in camera b (the renderer's truth).

    Each pixel's ray is cast from camera a into the terrain; the hit is projected into
    camera b, and counts as seen if it is inside b's image and the terrain does not hide it.

    Args:
        terrain: the surface the images show.
        camera: the camera model of both frames.
        world_T_cam_a, world_T_cam_b: (4, 4) camera poses.
        uv_a_px: (N, 2) pixels of camera a.

    Returns:
        ``uv_b_px`` (N, 2), NaN where not seen, and ``seen`` (N,) bool.
    """
    uv_a = np.asarray(uv_a_px, dtype=float).reshape(-1, 2)
    rays = camera.pixels_to_rays(uv_a) @ world_T_cam_a[:3, :3].T
    hits = terrain.raycast(world_T_cam_a[:3, 3], rays)
    seen, p_cam = visible_from(terrain, world_T_cam_b, np.nan_to_num(hits.point), hits.hit,
                               TRUTH_OCCLUSION_TOLERANCE_M)
    uv_b = camera.rays_to_pixels(p_cam)
    seen &= camera.in_image(uv_b)
    uv_b[~seen] = np.nan
    return uv_b, seen
