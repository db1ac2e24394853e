"""Synthetic terrain and the DTM height-error model (paper Figs. 6, 11, 12).

* :func:`fractal_terrain` makes the paper's nominal terrain: 3x3 km with 300 m of relief,
  a fractional-Brownian surface whose spectrum rolls off at a correlation length.
* :func:`clone_basic_cell` tiles a basic cell over a large flight region (Figs. 11-12).
* :func:`sigma_h_vs_grid_spacing` measures the height error of a coarser DTM against a
  fine one (Fig. 6); :func:`sigma_h_from_grid_spacing` is the linear model the rest of
  the package uses (defined in :mod:`cdtm_graph.dtm`, which must not import this module,
  and re-exported here).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cdtm_graph.dtm import SIGMA_H_PER_GRID_SPACING, Dtm, sigma_h_from_grid_spacing
from cdtm_graph.errors import DtmError

__all__ = [
    "NOMINAL_CORRELATION_LENGTH_M",
    "NOMINAL_HURST",
    "SIGMA_H_PER_GRID_SPACING",
    "clone_basic_cell",
    "fractal_terrain",
    "sigma_h_from_grid_spacing",
    "sigma_h_vs_grid_spacing",
]

NOMINAL_CORRELATION_LENGTH_M = 1500.0
"""Default roll-off length of :func:`fractal_terrain` (m): hills of a few hundred metres."""

NOMINAL_HURST = 1.0
"""Default Hurst exponent of :func:`fractal_terrain`.

Together with the correlation length it sets how much relief lies at short wavelengths,
hence the interpolation error of a coarse grid. These defaults give the paper's
sigma_h of about 2.4 m at 30 m spacing on the nominal 3x3 km, 300 m terrain (tests check
it), and a sigma_h that grows roughly linearly over 10..190 m, as in the paper's Fig. 6.
"""


def fractal_terrain(
    size_m: float = 3000.0,
    spacing_m: float = 5.0,
    relief_m: float = 300.0,
    correlation_length_m: float = NOMINAL_CORRELATION_LENGTH_M,
    hurst: float = NOMINAL_HURST,
    seed: int = 0,
    origin_xy: Sequence[float] = (0.0, 0.0),
) -> Dtm:
    """Random fractal terrain by spectral synthesis.

    White Gaussian noise is filtered in the Fourier domain by the amplitude
    ``(|k|^2 + k0^2)^(-(hurst + 1)/2)``, ``k0 = 1/correlation_length_m`` (cycles/m): a
    fractional-Brownian power law ``|k|^-(2H+2)`` at wavelengths shorter than the
    correlation length, flat (no ever-larger hills) beyond it. The result is shifted and
    scaled so that ``max - min == relief_m`` and the mean height is 0. The surface is
    periodic over ``n * spacing_m``, so :func:`clone_basic_cell` can also tile it.

    Args:
        size_m: side of the square region (m); the grid has
            ``round(size_m / spacing_m) + 1`` samples per side.
        spacing_m: sample spacing (m), dx = dy > 0.
        relief_m: max - min height (m), >= 0.
        correlation_length_m: roll-off wavelength (m), > 0.
        hurst: Hurst exponent in (0, 1]; higher is smoother at short scales.
        seed: seed of the random generator; the same seed gives the same terrain.
        origin_xy: world (x, y) of sample [0, 0] (m).

    Returns:
        A :class:`Dtm` with ``elevation[r, c]`` at ``origin + (c, r) * spacing_m``.
    """
    if not (spacing_m > 0 and size_m >= spacing_m and relief_m >= 0 and correlation_length_m > 0):
        raise DtmError(
            f"fractal_terrain(size_m={size_m}, spacing_m={spacing_m}, relief_m={relief_m}, "
            f"correlation_length_m={correlation_length_m}): expected spacing > 0, "
            "size >= spacing, relief >= 0, correlation length > 0"
        )
    if not 0.0 < hurst <= 1.0:
        raise DtmError(f"fractal_terrain: hurst = {hurst}, expected 0 < hurst <= 1")
    n = int(round(size_m / spacing_m)) + 1
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((n, n))
    k = np.fft.fftfreq(n, d=spacing_m)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    amplitude = (k2 + (1.0 / correlation_length_m) ** 2) ** (-(hurst + 1.0) / 2.0)
    amplitude[0, 0] = 0.0  # zero mean
    h = np.real(np.fft.ifft2(np.fft.fft2(noise) * amplitude))
    span = h.max() - h.min()
    h = h * (relief_m / span) if span > 0 else np.zeros_like(h)
    h -= h.mean()
    return Dtm(h, float(origin_xy[0]), float(origin_xy[1]), spacing_m, spacing_m)


def clone_basic_cell(cell: Dtm, nx: int, ny: int, mirror: bool = True) -> Dtm:
    """Tile a basic cell into a large DTM covering a flight region (paper Figs. 11-12).

    With ``mirror`` (default) every other tile is flipped along x (odd tile columns) and
    along y (odd tile rows), and neighbouring tiles share their edge samples, so the
    surface is continuous whatever the cell (the paper's cloned terrain has no cliffs at
    the seams); the result has ``nx*(cols-1)+1`` columns and ``ny*(rows-1)+1`` rows. With
    ``mirror=False`` the cell is repeated as is (``nx*cols`` columns, ``ny*rows`` rows):
    continuous only for a periodic cell such as :func:`fractal_terrain`'s.

    Args:
        cell: the basic cell; its (x0, y0, dx, dy) place tile (0, 0); ``sigma_h_m`` is kept.
        nx, ny: number of tiles along x (columns) and y (rows), >= 1.
        mirror: flip alternate tiles so the seams are continuous.

    Returns:
        The tiled :class:`Dtm`.
    """
    if int(nx) != nx or int(ny) != ny or nx < 1 or ny < 1:
        raise DtmError(f"clone_basic_cell: nx = {nx}, ny = {ny}, expected integers >= 1")
    e = np.asarray(cell.elevation)
    if mirror:
        # Drop the shared edge sample of every tile but the first along each axis.
        row_tiles = [e[:, ::-1] if t % 2 else e for t in range(nx)]
        strip = np.concatenate([row_tiles[0]] + [tile[:, 1:] for tile in row_tiles[1:]], axis=1)
        col_tiles = [strip[::-1, :] if t % 2 else strip for t in range(ny)]
        tiled = np.concatenate([col_tiles[0]] + [tile[1:, :] for tile in col_tiles[1:]], axis=0)
    else:
        tiled = np.tile(e, (int(ny), int(nx)))
    return Dtm(tiled, cell.x0, cell.y0, cell.dx, cell.dy, sigma_h_m=cell.sigma_h_m)


def sigma_h_vs_grid_spacing(fine: Dtm, spacings_m: Sequence[float]) -> np.ndarray:
    """RMS height error of coarser DTMs against a fine one, per grid spacing (paper Fig. 6).

    For each spacing the fine surface is point-sampled onto the coarse grid
    (:meth:`Dtm.resample`), the coarse bilinear surface is evaluated back at the fine
    sample positions, and the RMS of the difference is taken over the fine samples that
    the coarse grid covers and where both have data.

    Args:
        fine: the reference DTM (its samples are taken as the truth).
        spacings_m: (S,) coarse spacings (m).

    Returns:
        (S,) sigma_h in metres.
    """
    rows, cols = fine.shape
    xs = fine.x0 + np.arange(cols) * fine.dx
    ys = fine.y0 + np.arange(rows) * fine.dy
    truth = np.asarray(fine.elevation)
    sigmas = np.empty(len(spacings_m))
    for n, spacing in enumerate(spacings_m):
        coarse = fine.resample(float(spacing))
        diff = coarse.height(xs[None, :], ys[:, None]) - truth
        valid = np.isfinite(diff)
        if not valid.any():
            raise DtmError(f"sigma_h_vs_grid_spacing: no valid point at spacing {spacing} m")
        sigmas[n] = float(np.sqrt(np.mean(diff[valid] ** 2)))
    return sigmas
