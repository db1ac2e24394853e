"""Tests of cdtm_graph.sim.terrain: synthetic terrain, basic-cell cloning, the sigma_h model."""

from __future__ import annotations

import numpy as np
import pytest

from cdtm_graph import dtm as dtm_module
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import DtmError
from cdtm_graph.sim import terrain
from cdtm_graph.sim.terrain import (
    clone_basic_cell,
    fractal_terrain,
    sigma_h_from_grid_spacing,
    sigma_h_vs_grid_spacing,
)

EXACT_TOL_M = 1e-9
PAPER_SIGMA_H_AT_30M = 2.4  # m, the paper's nominal DTM (30 m grid, 300 m relief)
MODEL_FACTOR = 1.5  # how far our terrain's measured sigma_h may be from the linear model
FIG6_SPACINGS_M = np.array([10.0, 20.0, 30.0, 50.0, 70.0, 100.0, 130.0, 160.0, 190.0])
MIN_LINEAR_FIT_R2 = 0.98


def test_fractal_terrain_grid_relief_mean_and_determinism(seed):
    a = fractal_terrain(size_m=1000.0, spacing_m=10.0, relief_m=120.0, seed=seed, origin_xy=(5, -7))
    assert a.shape == (101, 101)
    assert (a.x0, a.y0, a.dx, a.dy) == (5.0, -7.0, 10.0, 10.0)
    assert np.nanmax(a.elevation) - np.nanmin(a.elevation) == pytest.approx(120.0, abs=EXACT_TOL_M)
    assert abs(a.elevation.mean()) < EXACT_TOL_M
    b = fractal_terrain(size_m=1000.0, spacing_m=10.0, relief_m=120.0, seed=seed,
                        origin_xy=(5, -7))
    np.testing.assert_array_equal(a.elevation, b.elevation)
    c = fractal_terrain(size_m=1000.0, spacing_m=10.0, relief_m=120.0, seed=seed + 1,
                        origin_xy=(5, -7))
    assert np.abs(a.elevation - c.elevation).max() > 10.0
    flat = fractal_terrain(size_m=100.0, spacing_m=10.0, relief_m=0.0)
    np.testing.assert_array_equal(flat.elevation, 0.0)


def test_fractal_terrain_roughness_follows_its_parameters(seed):
    """A shorter correlation length or a lower Hurst exponent puts more relief at short
    wavelengths: the coarse-grid height error rises."""
    spacing = [30.0]
    nominal = sigma_h_vs_grid_spacing(fractal_terrain(seed=seed), spacing)[0]
    short = sigma_h_vs_grid_spacing(
        fractal_terrain(correlation_length_m=500.0, seed=seed), spacing
    )[0]
    rough = sigma_h_vs_grid_spacing(fractal_terrain(hurst=0.7, seed=seed), spacing)[0]
    assert short > 1.3 * nominal and rough > 1.3 * nominal


@pytest.mark.parametrize(
    "kwargs", [dict(spacing_m=0.0), dict(relief_m=-1.0), dict(hurst=1.5), dict(size_m=1.0)]
)
def test_fractal_terrain_rejects_bad_parameters(kwargs):
    with pytest.raises(DtmError):
        fractal_terrain(**kwargs)


def test_clone_basic_cell_mirrored_tiles_are_continuous(rng):
    e = rng.uniform(0.0, 10.0, (5, 4))
    cell = Dtm(e, 100.0, 200.0, 3.0, -2.0, sigma_h_m=1.0)
    big = clone_basic_cell(cell, nx=3, ny=2)
    assert big.shape == (2 * 4 + 1, 3 * 3 + 1)
    assert (big.x0, big.y0, big.dx, big.dy, big.sigma_h_m) == (100.0, 200.0, 3.0, -2.0, 1.0)
    g = big.elevation
    np.testing.assert_array_equal(g[0:5, 0:4], e)  # tile (0, 0) as is
    np.testing.assert_array_equal(g[0:5, 3:7], e[:, ::-1])  # tile (0, 1) mirrored in x
    np.testing.assert_array_equal(g[0:5, 6:10], e)  # tile (0, 2)
    np.testing.assert_array_equal(g[4:9, 0:4], e[::-1, :])  # tile (1, 0) mirrored in y
    np.testing.assert_array_equal(g[4:9, 3:7], e[::-1, ::-1])
    # No seam is steeper than the cell itself.
    assert np.abs(np.diff(g, axis=1)).max() <= np.abs(np.diff(e, axis=1)).max()
    assert np.abs(np.diff(g, axis=0)).max() <= np.abs(np.diff(e, axis=0)).max()


def test_clone_basic_cell_plain_tiling_and_validation():
    e = np.arange(6.0).reshape(2, 3)
    cell = Dtm(e, 0.0, 0.0, 1.0, 1.0)
    plain = clone_basic_cell(cell, nx=2, ny=3, mirror=False)
    np.testing.assert_array_equal(plain.elevation, np.tile(e, (3, 2)))
    with pytest.raises(DtmError):
        clone_basic_cell(cell, nx=0, ny=1)


def test_sigma_h_vs_grid_spacing_is_zero_for_a_plane_and_exact_for_a_parabola():
    xs = np.arange(0.0, 601.0, 1.0)
    plane = Dtm(0.3 * xs[None, :] - 0.2 * xs[:, None] + 4.0, 0.0, 0.0, 1.0, 1.0)
    np.testing.assert_allclose(sigma_h_vs_grid_spacing(plane, [10.0, 30.0]), 0.0, atol=1e-9)
    # h = c x^2: a coarse grid (spacing s) interpolates linearly between its samples, so the
    # error at a fine point is c s^2 u (1 - u), u its fractional position in the coarse cell.
    c = 0.01
    parabola = Dtm(np.broadcast_to(c * xs[None, :] ** 2, (3, xs.size)), 0.0, 0.0, 1.0, 100.0)
    for s in (10.0, 30.0, 60.0):
        u = (xs / s) % 1.0
        expected = np.sqrt(np.mean((c * s**2 * u * (1 - u)) ** 2))
        assert sigma_h_vs_grid_spacing(parabola, [s])[0] == pytest.approx(expected, rel=1e-9)


def test_sigma_h_model_is_the_papers_and_defined_once():
    assert sigma_h_from_grid_spacing(30.0) == pytest.approx(PAPER_SIGMA_H_AT_30M)
    assert sigma_h_from_grid_spacing(190.0) == pytest.approx(190.0 * 0.08)
    assert terrain.sigma_h_from_grid_spacing is dtm_module.sigma_h_from_grid_spacing
    assert Dtm(np.zeros((2, 2)), 0, 0, 30.0, -20.0).sigma_h() == pytest.approx(2.4)
    with pytest.raises(DtmError):
        sigma_h_from_grid_spacing(0.0)


def test_nominal_terrain_reproduces_the_papers_fig6(seed):
    """On the nominal 3x3 km, 300 m-relief terrain, sigma_h at 30 m is the paper's 2.4 m and
    the curve over 10..190 m is close to the linear model everywhere."""
    fine = fractal_terrain(seed=seed)
    assert fine.grid_spacing_m == 5.0 and fine.bounds == (0.0, 3000.0, 0.0, 3000.0)
    sigma = sigma_h_vs_grid_spacing(fine, FIG6_SPACINGS_M)
    model = np.array([sigma_h_from_grid_spacing(s) for s in FIG6_SPACINGS_M])
    at_30 = sigma[FIG6_SPACINGS_M == 30.0][0]
    assert PAPER_SIGMA_H_AT_30M / MODEL_FACTOR < at_30 < PAPER_SIGMA_H_AT_30M * MODEL_FACTOR
    assert np.all(np.diff(sigma) > 0)
    ratio = sigma / model
    assert ratio.min() > 1 / MODEL_FACTOR and ratio.max() < MODEL_FACTOR
    # Linear in the spacing: a line through the origin explains the curve.
    slope = (sigma @ FIG6_SPACINGS_M) / (FIG6_SPACINGS_M @ FIG6_SPACINGS_M)
    residual = sigma - slope * FIG6_SPACINGS_M
    r2 = 1.0 - residual @ residual / np.sum((sigma - sigma.mean()) ** 2)
    assert r2 > MIN_LINEAR_FIT_R2


def test_sigma_h_at_30m_is_stable_across_seeds(seed):
    sigma_30 = [sigma_h_vs_grid_spacing(fractal_terrain(seed=s), [30.0])[0]
                for s in range(seed, seed + 4)]
    assert all(PAPER_SIGMA_H_AT_30M / MODEL_FACTOR < s < PAPER_SIGMA_H_AT_30M * MODEL_FACTOR
               for s in sigma_30)
