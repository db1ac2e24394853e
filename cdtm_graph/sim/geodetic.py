"""Simulated flights in geodetic coordinates: world terrain written as DEM tiles in any CRS.

The simulator's world is a local ENU plane; with a :class:`~cdtm_graph.geodesy.LocalFrame`
it is the tangent plane at a geodetic origin, and its terrain a surface over it.
:func:`write_dem_tile` writes that surface as a GeoTIFF in any CRS the way a public DEM
holds it (SRTM, Copernicus: EPSG:4326, heights above the EGM96 geoid; or UTM): each
pixel holds the height, above the ellipsoid or the geoid, of the terrain point at the
pixel centre's latitude and longitude. Reading the tile back with
:func:`cdtm_graph.dem.import_dem` must give the world terrain again, up to interpolation.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import SimulationError
from cdtm_graph.geodesy import GeodeticOrigin, LocalFrame, VerticalDatum, geoid_undulation_m

if TYPE_CHECKING:  # (the simulator writes through this module)
    from cdtm_graph.sim.simulate import SimulationResult

#: Name of the DEM tile in a simulated geodetic log directory.
GEODETIC_DEM_FILENAME = "dem.tif"

#: The height iteration stops when no pixel moved more than this (m).
_CONVERGENCE_M = 1e-5
_MAX_ITERATIONS = 12


def terrain_ellipsoidal_height_m(terrain: Dtm, frame: LocalFrame, latitude_deg: np.ndarray,
                                 longitude_deg: np.ndarray) -> np.ndarray:
    """Ellipsoidal height of a world terrain at geodetic latitudes and longitudes.

    Finds h with ``geodetic_to_world(lat, lon, h)`` on the surface ``z = terrain(x, y)``:
    moving along the point's own vertical by ``dh`` moves its world z by ``dh * up_z``.

    Args:
        terrain: world-frame terrain. latitude_deg, longitude_deg: (N,) degrees.

    Returns:
        (N,) heights (m); NaN where the vertical leaves the terrain grid.
    """
    lat = np.asarray(latitude_deg, dtype=float).ravel()
    lon = np.asarray(longitude_deg, dtype=float).ravel()
    up_z = frame.up_z(lat, lon)
    h = np.zeros(lat.size)
    out = np.full(lat.size, np.nan)
    active = np.arange(lat.size)
    for _ in range(_MAX_ITERATIONS):
        p = frame.geodetic_to_world(lat[active], lon[active], h[active])
        step = (terrain.height(p[:, 0], p[:, 1]) - p[:, 2]) / up_z[active]
        ok = np.isfinite(step)
        active, step = active[ok], step[ok]
        h[active] += step
        done = np.abs(step) <= _CONVERGENCE_M
        out[active[done]] = h[active[done]]
        active = active[~done]
        if active.size == 0:
            break
    return out


def write_dem_tile(terrain: Dtm, frame: LocalFrame, path: str | os.PathLike, crs: str,
                   pixel_size: float, vertical_datum: VerticalDatum = VerticalDatum.ELLIPSOID,
                   margin_px: int = 2) -> Path:
    """Write a world terrain as a north-up GeoTIFF in ``crs``, covering its extent.

    Args:
        terrain: world-frame terrain (the truth).
        frame: where the world is on the Earth.
        path: the .tif to write.
        crs: e.g. ``"EPSG:4326"`` or ``"EPSG:32652"``.
        pixel_size: in the CRS's units (degrees for EPSG:4326).
        vertical_datum: heights above the ellipsoid or above the EGM96 geoid.
        margin_px: pixels beyond the terrain's outline (no data there).

    Returns:
        The path. Pixels whose terrain point is off the world grid hold NaN (nodata).
    """
    import rasterio
    from affine import Affine
    from pyproj import Transformer

    xmin, xmax, ymin, ymax = terrain.bounds
    corners = np.array([[x, y, 0.0] for x in (xmin, xmax) for y in (ymin, ymax)])
    t = np.linspace(0.0, 1.0, 33)
    edge = np.concatenate([np.column_stack([xmin + (xmax - xmin) * t, np.full_like(t, y)])
                           for y in (ymin, ymax)]
                          + [np.column_stack([np.full_like(t, x), ymin + (ymax - ymin) * t])
                             for x in (xmin, xmax)])
    outline = np.vstack([corners, np.column_stack([edge, np.zeros(len(edge))])])
    lat, lon, _ = frame.world_to_geodetic(outline)
    to_crs = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    sx, sy = to_crs.transform(lon, lat)
    left = math.floor(min(sx) / pixel_size) * pixel_size - margin_px * pixel_size
    top = math.ceil(max(sy) / pixel_size) * pixel_size + margin_px * pixel_size
    width = int(math.ceil((max(sx) - left) / pixel_size)) + margin_px
    height = int(math.ceil((top - min(sy)) / pixel_size)) + margin_px
    cx = left + (np.arange(width) + 0.5) * pixel_size
    cy = top - (np.arange(height) + 0.5) * pixel_size
    gx, gy = np.meshgrid(cx, cy)
    plon, plat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(
        gx.ravel(), gy.ravel())
    plat, plon = np.asarray(plat), np.asarray(plon)
    h = terrain_ellipsoidal_height_m(terrain, frame, plat, plon)
    if vertical_datum is VerticalDatum.EGM96:
        h = h - geoid_undulation_m(plat, plon)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=1,
                       dtype="float32", crs=crs, nodata=float("nan"),
                       transform=Affine(pixel_size, 0.0, left, 0.0, -pixel_size, top)) as dst:
        dst.write(h.reshape(height, width).astype(np.float32), 1)
    return path


def origin_of(result: SimulationResult, origin: GeodeticOrigin | None) -> GeodeticOrigin:
    have = result.log.config.origin
    if have is None:
        raise SimulationError("a flat simulation written as a geodetic log: its IMU does not "
                              "sense the Earth; expected one simulated with "
                              "SimulationSettings(origin=...)")
    if origin is not None and origin != have:
        raise SimulationError(f"origin {origin} differs from the simulation's {have}; expected "
                              "the origin the flight was simulated at")
    return have


def write_geodetic_simulation_files(result: SimulationResult, directory: Path,
                                    origin: GeodeticOrigin | None = None,
                                    dem_crs: str = "EPSG:4326",
                                    pixel_size: float | None = None,
                                    vertical_datum: VerticalDatum = VerticalDatum.EGM96
                                    ) -> list[str]:
    """The geodetic log's files into ``directory`` (a staging directory), plainly.

    Returns:
        The names written.

    Raises:
        SimulationError: as :func:`~cdtm_graph.sim.simulate.write_geodetic_simulation`.
    """
    from pyproj import CRS

    from cdtm_graph.flightlog.writer import write_flightlog_files

    frame = LocalFrame(origin_of(result, origin))
    if pixel_size is None:
        pixel_size = (1.0 / 3600.0 if CRS.from_user_input(dem_crs).is_geographic
                      else result.dtm.grid_spacing_m)
    config = dataclasses.replace(result.log.config, dtm=dataclasses.replace(
        result.log.config.dtm, path=Path(GEODETIC_DEM_FILENAME), sigma_h_m=result.dtm.sigma_h_m,
        vertical_datum=vertical_datum))
    log = dataclasses.replace(result.log, config=config)
    write_dem_tile(result.terrain, frame, directory / GEODETIC_DEM_FILENAME, dem_crs,
                   pixel_size, vertical_datum)
    return [GEODETIC_DEM_FILENAME, *write_flightlog_files(log, directory, geodetic=True)]
