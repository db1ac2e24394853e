"""DEM import: any CRS, windowed reads, mosaics, Earth curvature, vertical datums."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

rasterio = pytest.importorskip("rasterio")
from affine import Affine  # noqa: E402

from cdtm_graph.dem import import_dem, read_dem_sources  # noqa: E402
from cdtm_graph.dtm import Dtm, load_dtm  # noqa: E402
from cdtm_graph.errors import DtmError  # noqa: E402
from cdtm_graph.geodesy import (  # noqa: E402
    GeodeticOrigin,
    LocalFrame,
    VerticalDatum,
    geoid_undulation_m,
)
from cdtm_graph.sim.geodetic import write_dem_tile  # noqa: E402

ORIGIN = GeodeticOrigin(36.5, 127.25, 120.0)
UTM_52N = "EPSG:32652"
ARCSEC = 1.0 / 3600.0

#: Heights that bilinear interpolation reproduces exactly (constant, planar in the grid's
#: own coordinates) must come back to this (m): the resampling iteration stops at 0.1 mm.
EXACT_TOL_M = 1e-3
#: A smooth terrain (150 m amplitude, 6 and 4.5 km wavelengths) through three bilinear
#: stages (native 30 m grid, the tile, the world grid): each errs by at most
#: spacing^2 / 8 (|h_xx| + |h_yy|) = 0.05 m.
SMOOTH_TERRAIN_TOL_M = 0.15


def _frame() -> LocalFrame:
    return LocalFrame(ORIGIN)


def _write_tif(path, heights, crs, left, top, pixel, nodata=None, dtype="float32"):
    with rasterio.open(path, "w", driver="GTiff", width=heights.shape[1],
                       height=heights.shape[0], count=1, dtype=dtype, crs=crs,
                       nodata=nodata, transform=Affine(pixel, 0.0, left, 0.0, -pixel, top)) as dst:
        dst.write(heights.astype(dtype), 1)
    return path


def _geographic_tile(path, height_fn, west, north, cols, rows, pixel=ARCSEC, crs="EPSG:4326"):
    """A north-up EPSG:4326 tile whose pixel centres hold ``height_fn(lat, lon)``."""
    lon = west + (np.arange(cols) + 0.5) * pixel
    lat = north - (np.arange(rows) + 0.5) * pixel
    grid_lon, grid_lat = np.meshgrid(lon, lat)
    return _write_tif(path, height_fn(grid_lat, grid_lon), crs, west, north, pixel,
                      dtype="float64")


def _nodes(dtm: Dtm) -> np.ndarray:
    """(N, 3) world points of every grid node with data."""
    gx, gy = np.meshgrid(dtm.x0 + np.arange(dtm.shape[1]) * dtm.dx,
                         dtm.y0 + np.arange(dtm.shape[0]) * dtm.dy)
    p = np.column_stack([gx.ravel(), gy.ravel(), dtm.elevation.ravel()])
    return p[np.isfinite(p[:, 2])]


REGION = (26000.0, 30000.0, 16000.0, 19000.0)


# --------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("datum", list(VerticalDatum))
def test_heights_come_back_exactly_with_the_curvature_of_the_earth(tmp_path, datum):
    frame = _frame()
    lat0, lon0 = 36.6, 127.5  # ~25 km north-east of the origin

    def ellipsoidal(lat, lon):  # planar in latitude and longitude: bilinear reproduces it
        return 600.0 + 3000.0 * (lat - lat0) - 2000.0 * (lon - lon0)

    def stored(lat, lon):
        h = ellipsoidal(lat, lon)
        if datum is VerticalDatum.EGM96:
            h = h - geoid_undulation_m(lat.ravel(), lon.ravel()).reshape(lat.shape)
        return h

    west, north = lon0 - 0.05, lat0 + 0.05
    tile = _geographic_tile(tmp_path / "tile.tif", stored, west, north, 360, 360, 1 / 3600)
    dtm = import_dem([tile], frame, (20000.0, 24000.0, 9000.0, 12000.0), datum)
    p = _nodes(dtm)
    assert len(p) == dtm.elevation.size  # the window covers the region
    lat, lon, h = frame.world_to_geodetic(p)
    # Every node lies on the terrain: its ellipsoidal height is the DEM's at its lat/lon.
    assert np.abs(h - ellipsoidal(lat, lon)).max() < EXACT_TOL_M
    # ... which is well below the flat-world reading: the ground curves away (~45 m here).
    flat = ellipsoidal(lat, lon) - ORIGIN.height_m
    drop = flat - p[:, 2]
    distance = np.hypot(p[:, 0], p[:, 1])
    np.testing.assert_allclose(drop, distance**2 / (2 * 6.37e6), rtol=0.01)


def test_epsg4326_utm_and_the_native_grid_agree(synthetic, tmp_path):
    frame = _frame()
    native = synthetic.smooth_native_dtm()
    geographic = write_dem_tile(native, frame, tmp_path / "g.tif", "EPSG:4326", ARCSEC,
                                VerticalDatum.EGM96)
    utm = write_dem_tile(native, frame, tmp_path / "u.tif", UTM_52N, 30.0,
                         VerticalDatum.ELLIPSOID)
    from_geographic = import_dem([geographic], frame, REGION, VerticalDatum.EGM96,
                                 spacing_m=25.0)
    from_utm = import_dem([utm], frame, REGION, VerticalDatum.ELLIPSOID, spacing_m=25.0)
    assert from_geographic.shape == from_utm.shape
    p = _nodes(from_geographic)
    assert len(p) == from_geographic.elevation.size
    assert np.abs(p[:, 2] - native.height(p[:, 0], p[:, 1])).max() < SMOOTH_TERRAIN_TOL_M
    q = _nodes(from_utm)
    assert np.abs(q[:, 2] - native.height(q[:, 0], q[:, 1])).max() < SMOOTH_TERRAIN_TOL_M
    # Read as egm96 heights the UTM tile (ellipsoidal) would sit N ~ 27 m too high.
    wrong = import_dem([utm], frame, REGION, VerticalDatum.EGM96, spacing_m=25.0)
    assert np.nanmin(wrong.elevation - from_utm.elevation) > 20.0


def test_default_grid_is_half_the_dem_pixel_and_sigma_h_follows_the_dem(synthetic, tmp_path):
    from cdtm_graph.dtm import sigma_h_from_grid_spacing

    frame = _frame()
    utm = write_dem_tile(synthetic.smooth_native_dtm(), frame, tmp_path / "u.tif", UTM_52N, 30.0)
    dtm = import_dem([utm], frame, REGION, VerticalDatum.ELLIPSOID)
    assert dtm.dx == 15.0
    # The Fig. 6 model at the DEM's 30 m (not the grid's 15 m), plus a tiny resampling error.
    assert sigma_h_from_grid_spacing(30.0) <= dtm.sigma_h() < sigma_h_from_grid_spacing(30.0) + 0.01
    geographic = write_dem_tile(
        synthetic.smooth_native_dtm(), frame, tmp_path / "g.tif", "EPSG:4326", ARCSEC
    )
    spacing = import_dem([geographic], frame, REGION, VerticalDatum.ELLIPSOID).dx
    # Half of 1" of longitude at 36.7 deg N (the east-west pixel is the finer one).
    assert spacing == pytest.approx(0.5 * 30.92 * math.cos(math.radians(36.7)), rel=0.01)


def test_sigma_h_counts_the_resampling_error(synthetic, tmp_path, rng):
    frame = _frame()
    native = synthetic.smooth_native_dtm()
    utm = write_dem_tile(native, frame, tmp_path / "u.tif", UTM_52N, 30.0)
    fine = import_dem([utm], frame, REGION, VerticalDatum.ELLIPSOID, spacing_m=15.0,
                      sigma_h_m=0.1)
    coarse = import_dem([utm], frame, REGION, VerticalDatum.ELLIPSOID, spacing_m=90.0,
                        sigma_h_m=0.1)
    # Measured independently: the coarse grid's surface against the tile's own surface
    # (the fine grid stands in for it: its own resampling error is far smaller).
    x = rng.uniform(REGION[0] + 100, REGION[1] - 100, 5000)
    y = rng.uniform(REGION[2] + 100, REGION[3] - 100, 5000)
    rms = float(np.sqrt(np.mean((coarse.height(x, y) - fine.height(x, y)) ** 2)))
    assert rms > 0.1  # 90 m cells on 150 m hills 4.5 km apart: 0.15 m
    assert math.hypot(0.1, rms) == pytest.approx(coarse.sigma_h(), rel=0.1)
    assert fine.sigma_h() < 0.1 + 0.2 * (coarse.sigma_h() - 0.1)


# --------------------------------------------------------------------------- mosaics


def _split(tmp_path, whole, overlap: int):
    """Four quarter tiles of a 4326 tile, sharing ``overlap`` rows/columns (SRTM: 1,
    Copernicus: 0); the north-west one listed last."""
    with rasterio.open(whole) as src:
        data, t = src.read(1), src.transform
    rows, cols = data.shape
    r, c = rows // 2, cols // 2
    paths = []
    for name, (r0, r1, c0, c1) in {"se": (r, rows, c, cols), "sw": (r, rows, 0, c + overlap),
                                   "ne": (0, r + overlap, c, cols),
                                   "nw": (0, r + overlap, 0, c + overlap)}.items():
        paths.append(_write_tif(tmp_path / f"{name}.tif", data[r0:r1, c0:c1], "EPSG:4326",
                                t.c + c0 * t.a, t.f + r0 * t.e, t.a))
    return paths


@pytest.mark.parametrize("overlap", [0, 1])
def test_a_mosaic_of_tiles_is_the_whole_tile(synthetic, tmp_path, overlap):
    frame = _frame()
    whole = write_dem_tile(
        synthetic.smooth_native_dtm(), frame, tmp_path / "whole.tif", "EPSG:4326", ARCSEC
    )
    single = import_dem([whole], frame, REGION, VerticalDatum.ELLIPSOID)
    tiles = import_dem(_split(tmp_path, whole, overlap), frame, REGION,
                       VerticalDatum.ELLIPSOID)
    # Same pixels, same nodes; only the grid origin is computed from another tile's corner.
    np.testing.assert_allclose(tiles.elevation, single.elevation, rtol=0, atol=1e-6)


def test_tiles_off_the_pixel_grid_are_refused(tmp_path):
    a = _write_tif(tmp_path / "a.tif", np.zeros((50, 50)), "EPSG:4326", 127.5, 36.7, ARCSEC)
    b = _write_tif(tmp_path / "b.tif", np.zeros((50, 50)), "EPSG:4326",
                   127.5 + 50.5 * ARCSEC, 36.7, ARCSEC)
    with pytest.raises(DtmError, match=r"b\.tif: its pixels are offset"):
        import_dem([a, b], _frame(), (22000.0, 24000.0, 21000.0, 22000.0),
                   VerticalDatum.ELLIPSOID)


def test_tiles_in_different_crss_fill_each_other(synthetic, tmp_path):
    frame = _frame()
    native = synthetic.smooth_native_dtm()
    geographic = write_dem_tile(native, frame, tmp_path / "g.tif", "EPSG:4326", ARCSEC)
    with rasterio.open(geographic) as src:
        data, t = src.read(1), src.transform
    west_half = _write_tif(tmp_path / "west.tif", data[:, : data.shape[1] // 2], "EPSG:4326",
                           t.c, t.f, t.a)
    utm = write_dem_tile(native, frame, tmp_path / "u.tif", UTM_52N, 30.0)
    dtm = import_dem([west_half, utm], frame, REGION, VerticalDatum.ELLIPSOID, spacing_m=25.0)
    p = _nodes(dtm)
    assert len(p) == dtm.elevation.size  # the UTM tile fills the east
    assert np.abs(p[:, 2] - native.height(p[:, 0], p[:, 1])).max() < SMOOTH_TERRAIN_TOL_M


# --------------------------------------------------------------------------- formats


def test_ascii_grid_with_prj_reads_like_the_geotiff(synthetic, tmp_path):
    from pyproj import CRS

    frame = _frame()
    tif = write_dem_tile(synthetic.smooth_native_dtm(), frame, tmp_path / "u.tif", UTM_52N, 30.0)
    with rasterio.open(tif) as src:
        data, t = src.read(1).astype(float), src.transform
    rows, cols = data.shape
    lines = [f"ncols {cols}", f"nrows {rows}", f"xllcorner {t.c!r}",
             f"yllcorner {t.f + rows * t.e!r}", f"cellsize {t.a!r}", "NODATA_value -9999"]
    lines += [" ".join(repr(float(v)) for v in row)
              for row in np.where(np.isnan(data), -9999.0, data)]
    asc = tmp_path / "u.asc"
    asc.write_text("\n".join(lines) + "\n")
    (tmp_path / "u.prj").write_text(CRS.from_string(UTM_52N).to_wkt("WKT1_ESRI"))
    a = import_dem([asc], frame, REGION, VerticalDatum.ELLIPSOID)
    b = import_dem([tif], frame, REGION, VerticalDatum.ELLIPSOID)
    np.testing.assert_allclose(a.elevation, b.elevation, rtol=0, atol=1e-3)
    # Without its .prj the same grid has no CRS: refused, or placed by dtm.crs.
    (tmp_path / "u.prj").unlink()
    with pytest.raises(DtmError, match="carries no CRS"):
        import_dem([asc], frame, REGION, VerticalDatum.ELLIPSOID)
    c = import_dem([asc], frame, REGION, VerticalDatum.ELLIPSOID, crs=UTM_52N)
    np.testing.assert_allclose(c.elevation, b.elevation, rtol=0, atol=1e-3)


def test_a_vertical_crs_in_the_file_must_agree_with_the_datum(tmp_path):
    compound = _write_tif(tmp_path / "c.tif", np.full((40, 40), 300.0), "EPSG:4326+5773",
                          127.5, 36.7, ARCSEC)
    region = (22000.0, 22500.0, 21000.0, 21500.0)
    with pytest.raises(DtmError, match="dtm.vertical_datum is ellipsoid"):
        import_dem([compound], _frame(), region, VerticalDatum.ELLIPSOID)
    # The same 300 m above the geoid, read as EGM96, sits ~27 m higher above the ellipsoid.
    assert import_dem([compound], _frame(), region, VerticalDatum.EGM96).elevation.size


def test_no_data_under_the_flight_is_one_clear_error(tmp_path):
    far = _write_tif(tmp_path / "far.tif", np.zeros((30, 30)), "EPSG:4326", 10.0, 50.0, ARCSEC)
    with pytest.raises(DtmError, match=r"far\.tif: no data under the flight \(latitude 36"):
        import_dem([far], _frame(), REGION, VerticalDatum.ELLIPSOID)


def test_degree_valued_grids_without_a_crs_are_refused(tmp_path):
    asc = tmp_path / "srtm.asc"
    rows = "\n".join(" ".join(["100"] * 4) for _ in range(4))
    asc.write_text(f"ncols 4\nnrows 4\nxllcorner 127.0\nyllcorner 36.0\n"
                   f"cellsize 0.000277777777778\n{rows}\n")
    with pytest.raises(DtmError, match="looks like degrees"):
        load_dtm(asc)
    untagged = _write_tif(tmp_path / "untagged.tif", np.zeros((4, 4)), None, 127.0, 37.0,
                          ARCSEC)
    with pytest.raises(DtmError, match="looks like degrees"):
        load_dtm(untagged)
    geographic = _write_tif(tmp_path / "g.tif", np.zeros((4, 4)), "EPSG:4326", 127.0, 37.0,
                            ARCSEC)
    with pytest.raises(DtmError, match="top-level origin"):
        load_dtm(geographic)


# --------------------------------------------------------------------------- memory

#: Imports each tile given, in turn, in one process and prints the peak memory after each
#: (ru_maxrss, KiB on Linux): a peak only grows, so what the second tile adds over the first
#: is what it costs beyond it (one interpreter start instead of two).
_PEAK_SCRIPT = textwrap.dedent("""
    import resource, sys
    from cdtm_graph.dem import import_dem
    from cdtm_graph.geodesy import GeodeticOrigin, LocalFrame, VerticalDatum
    frame = LocalFrame(GeodeticOrigin(36.05, 127.05, 100.0))
    for path in sys.argv[1:]:
        dtm = import_dem([path], frame, (-5000.0, 5000.0, -5000.0, 5000.0),
                         VerticalDatum.EGM96)
        assert dtm.elevation.size > 100_000, dtm
        del dtm
        print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
""")

#: What a 3601 x 3601 tile may add to the peak memory over a 720 x 720 crop of it (MB;
#: the issue's limit is 100). Measured 2026-11-27: 0.0 (the window is all that is read);
#: the whole band read as float64 and cropped adds 99.5.
BIG_TILE_EXTRA_MB = 25.0


def _peaks_kib(*paths) -> list[int]:
    out = subprocess.run([sys.executable, "-c", _PEAK_SCRIPT, *map(str, paths)], check=True,
                         capture_output=True, text=True)
    return [int(v) for v in out.stdout.split()[-len(paths):]]


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ru_maxrss in KiB: Linux")
def test_a_3601_tile_costs_only_the_window_under_the_flight(tmp_path, rng):
    """Mutation: the whole band read as float64 and then cropped (in place of the windowed
    ``ds.read`` in ``dem._group_surface``) adds 99.5 MB and fails the bound."""
    # An SRTM 1" tile (N36E127, int16, 25.9 MB on disk; 104 MB as float64) and the same
    # heights cropped to a small tile around the flight, over one of its corners.
    heights = rng.integers(0, 800, size=(3601, 3601), dtype=np.int16)
    west, north = 127.0 - 0.5 * ARCSEC, 37.0 + 0.5 * ARCSEC
    big = _write_tif(tmp_path / "N36E127.tif", heights, "EPSG:4326", west, north, ARCSEC,
                     dtype="int16")
    r0, c0 = 3601 - 720, 0  # the south-west corner, 0.2 deg square
    small = _write_tif(tmp_path / "small.tif", heights[r0:, c0:720], "EPSG:4326",
                       west + c0 * ARCSEC, north - r0 * ARCSEC, ARCSEC, dtype="int16")
    del heights
    after_small, after_big = _peaks_kib(small, big)
    extra_mb = (after_big - after_small) / 1024
    assert extra_mb < BIG_TILE_EXTRA_MB, (after_small, after_big)


# --------------------------------------------------------------------------- smoothing

#: The georeferenced tile differs from the native grid by interpolation only (< 4 cm on
#: this terrain at 1/3"): the smoothed positions may differ by this Mahalanobis distance
#: under their own covariance (measured 0.046; 0.020 with a 1/9" tile, so it is the
#: interpolation, not the geodesy).
SAME_SMOOTHING_MAHALANOBIS = 0.1


@pytest.mark.slow
def test_a_flat_flight_smooths_the_same_over_npz_and_over_a_georeferenced_tile(seed, tmp_path):
    import dataclasses

    from cdtm_graph.dtm import save_dtm_npz
    from cdtm_graph.flightlog import DtmConfig, write_flightlog
    from cdtm_graph.graph import GraphSettings
    from cdtm_graph.results import pose_covariance_in_world
    from cdtm_graph.run.prepare import load_log_and_dtm
    from cdtm_graph.sim.simulate import SimulationSettings, simulate, write_simulation
    from cdtm_graph.smoother import SmootherSettings, smooth

    # Smooth terrain 20-30 km from the origin, on a 10 m grid (the truth the features are
    # cast on, and the flat log's DTM).
    x = 19980.0 + np.arange(901) * 10.0
    y = 9990.0 + np.arange(901) * 10.0
    gx, gy = np.meshgrid(x, y)
    z = (300.0 + 150.0 * np.sin(2 * np.pi * gx / 3000.0) * np.cos(2 * np.pi * gy / 2500.0)
         - (gx**2 + gy**2) / (2 * 6.37e6))
    save_dtm_npz(Dtm(z, x[0], y[0], 10.0, 10.0), tmp_path / "terrain.npz")
    sim = simulate(SimulationSettings(terrain=tmp_path / "terrain.npz", frames=12, seed=seed,
                                      altitude_m=800.0))
    cfg = sim.log.config
    flat_cfg = dataclasses.replace(cfg, dtm=dataclasses.replace(cfg.dtm, sigma_h_m=1.0))
    write_simulation(dataclasses.replace(sim, log=dataclasses.replace(sim.log, config=flat_cfg)),
                     tmp_path / "flat")
    # The same log with the world placed on the Earth and the terrain as an EGM96 tile.
    frame = _frame()
    write_dem_tile(sim.terrain, frame, tmp_path / "geo" / "dem.tif", "EPSG:4326", ARCSEC / 3,
                   VerticalDatum.EGM96)
    geo_cfg = dataclasses.replace(cfg, origin=ORIGIN, dtm=DtmConfig(
        tmp_path / "geo" / "dem.tif", 1.0, vertical_datum=VerticalDatum.EGM96, margin_m=1500.0))
    write_flightlog(dataclasses.replace(sim.log, config=geo_cfg), tmp_path / "geo")

    # The same samples on both sides: the flat IMU model for the log placed on the Earth
    # too (its simulated IMU senses no Earth: tests/smoother/test_earth_imu.py has the Earth's).
    flat_imu = SmootherSettings(graph=GraphSettings(earth_physics=False))
    results = [smooth(*load_log_and_dtm(tmp_path / name), flat_imu) for name in ("flat", "geo")]
    flat, geo = (r.estimate.position_m for r in results)
    _, cov = pose_covariance_in_world(results[0].estimate.world_T_body,
                                      results[0].covariances.pose)
    d = geo - flat
    mahalanobis = np.sqrt(np.einsum("ni,nij,nj->n", d, np.linalg.inv(cov), d))
    assert np.all(mahalanobis < SAME_SMOOTHING_MAHALANOBIS)
    assert results[1].counts.n_cdtm_features == results[0].counts.n_cdtm_features


# --------------------------------------------------------------------------- hostile input


def test_a_world_grid_beyond_the_node_cap_is_refused_before_it_is_allocated(synthetic, tmp_path):
    utm = write_dem_tile(synthetic.smooth_native_dtm(), _frame(), tmp_path / "u.tif", UTM_52N, 30.0)
    # 1 cm over the 4 x 3 km region: 1.2e11 nodes, 960 GB of heights
    with pytest.raises(DtmError) as info:
        import_dem([utm], _frame(), REGION, VerticalDatum.ELLIPSOID, spacing_m=0.01)
    message = str(info.value)
    assert message.startswith(f"{utm}: the world grid would be 400001 x 300001 = 1.2e+11 "
                              "nodes (960 GB) at a spacing of 0.01 m over 4 x 3 km"), message
    assert "expected at most 1e+09 nodes: a larger dtm.spacing_m or a smaller dtm.margin_m" \
        in message and "\n" not in message


def test_a_truncated_dem_tile_is_one_line_without_gdal_warnings(synthetic, tmp_path, caplog):
    import logging
    import warnings

    utm = write_dem_tile(synthetic.smooth_native_dtm(), _frame(), tmp_path / "u.tif", UTM_52N, 30.0)
    utm.write_bytes(utm.read_bytes()[:100])
    with caplog.at_level(logging.DEBUG), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(DtmError) as info:
            import_dem([utm], _frame(), REGION, VerticalDatum.ELLIPSOID)
    message = str(info.value)
    assert message.startswith(f"{utm}: cannot read it: the file is damaged, truncated or of "
                              "another format ("), message
    assert "See previous exception" not in message and "\n" not in message
    assert not [r for r in caplog.records if r.name.startswith("rasterio")], caplog.text
    assert not caught, [str(w.message) for w in caught]


def test_a_dem_tile_without_a_geotransform_is_refused(tmp_path):
    """A GeoTIFF with a CRS but no geotransform: rasterio places it at one CRS unit per
    pixel from (0, 0); the DEM import read it there without a word (a review found it)."""
    import rasterio

    path = tmp_path / "nogeo.tif"
    with rasterio.open(path, "w", driver="GTiff", width=3, height=3, count=1,
                       dtype="float32", crs="EPSG:4326") as dst:
        dst.write(np.full((1, 3, 3), 100.0, np.float32))
    with pytest.raises(DtmError, match=r"nogeo\.tif: no georeferencing \(no geotransform\)"):
        import_dem([path], _frame(), REGION, VerticalDatum.ELLIPSOID)


def test_a_dem_in_feet_is_refused_naming_the_unit(tmp_path):
    """A GeoTIFF in a US State Plane CRS (EPSG:2227, US survey feet): refused, naming the
    unit, since its heights (most often feet) would be read as metres. Mutation tried: the
    check off (the run failed as map_mismatch and wrong_fix, the unit never named: a
    hostile-input hunt's find, 2026-11-28)."""
    feet = _write_tif(tmp_path / "feet.tif", np.full((40, 40), 1000.0), "EPSG:2227",
                      6_000_000.0, 2_100_000.0, 30.0)
    with pytest.raises(DtmError, match=r"feet\.tif: its CRS .* is in US survey foot units, and "
                                       r"the unit of its heights cannot be told"):
        import_dem([feet], _frame(), REGION, VerticalDatum.ELLIPSOID)


def test_a_dem_in_feet_with_its_heights_stated_in_metres_is_read(tmp_path):
    """The same CRS in feet with an EGM96 height (metres) beside it: the unit of the
    heights is stated, so the file is read (not refused as in feet)."""
    stated = _write_tif(tmp_path / "stated.tif", np.full((40, 40), 1000.0),
                        "EPSG:2227+5773", 6_000_000.0, 2_100_000.0, 30.0)
    assert len(read_dem_sources([stated], VerticalDatum.EGM96)) == 1
