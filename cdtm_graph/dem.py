"""DEM import: tiles in any CRS, read under the flight only, resampled into the world grid.

A geodetic flight log (``origin:`` in flight.yaml) names its DEM as one or several files
(GeoTIFF, ``.asc`` with a ``.prj`` beside it, SRTM ``.hgt``) in any horizontal CRS,
geographic (EPSG:4326: SRTM, Copernicus GLO-30) or projected (UTM...), with heights above
the WGS84 ellipsoid or the EGM96 geoid. :func:`import_dem` turns them into the
:class:`~cdtm_graph.dtm.Dtm` the estimator uses, a regular grid of *world* heights over
the local ENU plane:

1. **Window.** The world region (the flight's footprint, :func:`track_region_m`) is
   mapped into each file's CRS (its outline at the lowest and highest terrain heights on
   Earth, so that the lean of the verticals away from the origin is covered), padded by
   ``WINDOW_PAD_PX`` pixels, and only that window is read (rasterio windowed reads):
   memory follows the footprint, not the tile.
2. **Mosaic.** Files that share a CRS and pixel size must share one pixel grid; their
   windows are pasted into one array (the first file listed wins where they overlap), so
   tiles that abut without overlapping (Copernicus) leave no seam. Files in different
   CRSs are sampled in turn: the first with data at a point wins.
3. **Resample, Earth curvature included.** Every node ``(x, y)`` of the world grid gets
   the world z of the terrain point whose world x and y are exactly ``(x, y)``: starting
   on the tangent plane, ``(x, y, z)`` goes to latitude, longitude and ellipsoidal height
   h (PROJ), the DEM gives the terrain's ellipsoidal height H there (bilinear on the
   source grid, plus the EGM96 undulation for ``egm96`` heights), and z moves by
   ``(H - h) / up_z`` (``up_z``: world z of the point's local vertical) until no node moves
   more than ``CONVERGENCE_M``. The ground's drop below the tangent plane (67 m at 29 km)
   and the lean of the local vertical are therefore in the grid. The iteration contracts by
   about (terrain slope) x (distance / Earth radius) per step: 3 steps to 0.1 mm for 100 km
   and slopes of 1; a node that does not converge (a cliff far out) becomes no data.

The world grid's spacing is half the source's finest pixel size in metres at the region's
centre (``SPACING_PER_PIXEL``); its nodes lie on multiples of the spacing from the world
origin, so two regions of one DEM agree node for node where they overlap. Its sigma_h is
the DEM's own (given, or the Fig. 6 model at the DEM's pixel size) combined with the
resampling error, measured at ``RESAMPLING_CHECK_POINTS`` points.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdtm_graph.dtm import Dtm, gdal_quiet, gdal_reason, sigma_h_from_grid_spacing
from cdtm_graph.errors import DtmError, why_not_a_file
from cdtm_graph.geodesy import (
    WGS84_A_M,
    WGS84_E2,
    LocalFrame,
    VerticalDatum,
    ellipsoidal_height_m,
)

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_MARGIN_M",
    "DEM_SUFFIXES",
    "DemSource",
    "DemWindow",
    "import_dem",
    "read_dem_window",
    "read_dem_sources",
    "track_region_m",
]

#: File types :func:`import_dem` reads (through GDAL).
DEM_SUFFIXES = (".tif", ".tiff", ".asc", ".hgt")
#: Margin around the prior track (m) when flight.yaml gives no ``dtm.margin_m``: the
#: footprint of a 60 deg camera banked 30 deg from 1.9 km above the ground, plus the prior.
DEFAULT_MARGIN_M = 5000.0
#: Source pixels read beyond the footprint on each side (a bilinear cell needs both corners).
WINDOW_PAD_PX = 2
#: Ellipsoidal heights between which terrain exists on Earth (m): the Dead Sea shore to
#: above Everest, geoid included.
LOWEST_TERRAIN_M = -600.0
HIGHEST_TERRAIN_M = 9000.0
#: The resampling iteration stops when no node moves more than this (m).
CONVERGENCE_M = 1e-4
#: ... or after this many steps; nodes still moving become no data.
MAX_ITERATIONS = 12
#: World nodes resampled per batch (bounds the temporaries: ~30 float64 arrays of this size).
CHUNK_NODES = 1 << 18
#: Default world grid spacing as a fraction of the DEM's finest pixel (in metres): a
#: bilinear surface resampled at its own pixel size errs by about as much as the DEM's own
#: interpolation (1.35 m rms on a 1" tile of fractal terrain whose sigma_h is 2.4 m), at
#: half of it by far less (0.28 m; docs/geodesy.md).
SPACING_PER_PIXEL = 0.5
#: Most nodes of the world grid :func:`import_dem` makes (8 GB of float64 heights, e.g.
#: 474 x 474 km at 15 m, a 30 m DEM's default spacing): beyond it the region (the prior
#: track plus ``dtm.margin_m``) or the spacing (``dtm.spacing_m``) is a typo, refused
#: before anything is allocated.
MAX_GRID_NODES = 1_000_000_000
#: Points at which the resampling error is measured (folded into sigma_h).
RESAMPLING_CHECK_POINTS = 4096
#: Points per edge of the region outline mapped into a source CRS.
_OUTLINE_POINTS = 65


@dataclass(frozen=True)
class DemSource:
    """One DEM file's georeferencing (no pixels).

    Attributes:
        path: the file.
        crs_wkt: its horizontal CRS as WKT.
        transform: (a, c, e, f): pixel (col, row)'s outer corner is ``(c + col a, f + row e)``
            in CRS units; ``a > 0``, ``e`` of either sign.
        width, height: pixels.
        scale, offset: raw value -> height ``raw * scale + offset``.
        is_geographic: True for a latitude/longitude CRS.
    """

    path: Path
    crs_wkt: str
    transform: tuple[float, float, float, float]
    width: int
    height: int
    scale: float = 1.0
    offset: float = 0.0
    is_geographic: bool = False

    def pixel_size_m(self, latitude_deg: float) -> float:
        """The finer of the two pixel sizes in metres near ``latitude_deg``."""
        a, _, e, _ = self.transform
        if not self.is_geographic:
            from pyproj import CRS

            factor = CRS.from_wkt(self.crs_wkt).axis_info[0].unit_conversion_factor or 1.0
            return min(abs(a), abs(e)) * factor
        s2 = math.sin(math.radians(latitude_deg)) ** 2
        n_radius = WGS84_A_M / math.sqrt(1 - WGS84_E2 * s2)
        m_radius = n_radius * (1 - WGS84_E2) / (1 - WGS84_E2 * s2)
        deg = math.pi / 180.0
        return min(abs(a) * deg * n_radius * math.cos(math.radians(latitude_deg)),
                   abs(e) * deg * m_radius)


def _fail(path: Path | str, what: str, expected: str) -> DtmError:
    return DtmError(f"{path}: {what}; expected {expected}")


def _horizontal_crs(path: Path, crs_wkt: str, datum: VerticalDatum):
    """The horizontal part of a file's CRS; a vertical part must agree with ``datum``."""
    from pyproj import CRS

    crs = CRS.from_wkt(crs_wkt)
    if crs.is_compound:
        horizontal, vertical = crs.sub_crs_list[0], crs.sub_crs_list[1]
        is_egm96 = "egm96" in vertical.name.lower().replace(" ", "")
        if not is_egm96:
            raise _fail(path, f"vertical CRS {vertical.name!r} is not supported",
                        "ellipsoidal heights or heights above the EGM96 geoid")
        if datum is not VerticalDatum.EGM96:
            raise _fail(path, f"its CRS says heights above {vertical.name} but "
                        f"dtm.vertical_datum is {datum.value}", "the two to agree (egm96)")
        return horizontal
    if len(crs.axis_info) == 3 and crs.is_geographic and datum is not VerticalDatum.ELLIPSOID:
        raise _fail(path, f"its CRS {crs.name!r} has ellipsoidal heights but "
                    f"dtm.vertical_datum is {datum.value}", "the two to agree (ellipsoid)")
    if len(crs.axis_info) == 3:
        return crs.to_2d()
    return crs


def _check_metres(path: Path, horizontal) -> None:
    """Refuse a projected CRS in another unit than the metre, unless a vertical CRS states
    the heights' (a compound one: checked to be EGM96, in metres): the heights are read as
    metres, and a file in feet (US State Plane) most often holds heights in feet too,
    which nothing in it says (x and y would be converted, z not: 3.28x too high)."""
    if horizontal.is_geographic or not horizontal.axis_info:
        return
    axis = horizontal.axis_info[0]
    if abs(float(axis.unit_conversion_factor or 1.0) - 1.0) > 1e-12:
        raise _fail(path, f"its CRS {horizontal.name!r} is in {axis.unit_name} units, and the "
                    "unit of its heights cannot be told (often the same)",
                    "a DEM in metres (reproject it to a metric CRS, e.g. `gdalwarp -t_srs "
                    "EPSG:32610`, and scale its heights to metres)")


def read_dem_sources(paths: Sequence[str | os.PathLike], vertical_datum: VerticalDatum,
                     crs: str | None = None) -> list[DemSource]:
    """Open DEM files and read their georeferencing (no pixels).

    Args:
        paths: the files, in priority order (the first with data at a point wins).
        vertical_datum: what the heights are measured from (checked against a vertical
            CRS in the file, if any).
        crs: the CRS (e.g. ``"EPSG:32652"``) of files that carry none; a file with its own
            CRS keeps it, and must agree.

    Returns:
        One :class:`DemSource` per file.

    Raises:
        DtmError: unreadable file, no CRS, rotated grid, disagreeing CRS.
    """
    import rasterio
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    override = None
    if crs is not None:
        try:
            override = CRS.from_user_input(crs)
        except CRSError as exc:
            raise DtmError(f"dtm.crs {crs!r} is not a CRS PROJ knows ({exc}); "
                           "expected e.g. EPSG:4326 or EPSG:32652") from None
    sources = []
    for given in paths:
        path = Path(given)
        if path.suffix.lower() not in DEM_SUFFIXES:
            raise _fail(path, f"unknown DEM file type {path.suffix!r}",
                        f"one of {', '.join(DEM_SUFFIXES)}")
        if not path.is_file():
            raise _fail(path, why_not_a_file(path), "a DEM file")
        with gdal_quiet() as notes:  # GDAL's warnings on a damaged file: in the message
            try:
                with rasterio.open(path) as src:
                    file_crs = src.crs
                    t = src.transform
                    width, height, count = src.width, src.height, src.count
                    scale = float(src.scales[0]) if src.scales else 1.0
                    offset = float(src.offsets[0]) if src.offsets else 0.0
            except Exception as exc:  # rasterio raises its own types; report them all alike
                raise _fail(path, "cannot read it: the file is damaged, truncated or of "
                            f"another format ({gdal_reason(exc, notes)})",
                            "a GeoTIFF, an ESRI .asc grid or an SRTM .hgt tile") from None
        if notes.not_georeferenced:  # rasterio would place it at 1 CRS unit per pixel
            raise _fail(path, "no georeferencing (no geotransform): its pixels have no "
                        "coordinates", "a georeferenced DEM")
        if count < 1:
            raise _fail(path, "no raster band", "one band of heights")
        if t.b != 0.0 or t.d != 0.0:
            raise _fail(path, f"the grid is rotated or sheared (b={t.b}, d={t.d})",
                        "a north-up, axis-aligned grid")
        if file_crs is None:
            if override is None:
                raise _fail(path, "the file carries no CRS",
                            "a georeferenced GeoTIFF, an .asc with its .prj beside it, or "
                            "dtm.crs in flight.yaml naming the CRS")
            wkt = override.to_wkt()
        else:
            wkt = file_crs.to_wkt()
            if override is not None and not CRS.from_wkt(wkt).equals(override):
                raise _fail(path, f"its own CRS {CRS.from_wkt(wkt).name!r} differs from "
                            f"dtm.crs {crs!r}", "dtm.crs only for files without a CRS")
        horizontal = _horizontal_crs(path, wkt, vertical_datum)
        if not CRS.from_wkt(wkt).is_compound:  # (a compound CRS's heights: EGM96 metres)
            _check_metres(path, horizontal)
        sources.append(DemSource(path, horizontal.to_wkt(), (t.a, t.c, t.e, t.f), width,
                                 height, scale, offset, horizontal.is_geographic))
    if not sources:
        raise DtmError("no DEM file given; expected one or more")
    return sources


def track_region_m(track_xy_m: np.ndarray, margin_m: float
                   ) -> tuple[float, float, float, float]:
    """The world region under a flight: the track's bounding box grown by a margin.

    Args:
        track_xy_m: (N, 2) world x, y of the prior track (initial state, nav.csv or IMU
            dead reckoning), metres; non-finite rows are ignored.
        margin_m: added on every side (m), >= 0.

    Returns:
        (xmin, xmax, ymin, ymax) in metres.
    """
    xy = np.asarray(track_xy_m, dtype=float).reshape(-1, 2)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if xy.size == 0:
        raise DtmError("the flight has no finite position to place the DEM window around; "
                       "expected an initial_state position")
    lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


# --------------------------------------------------------------------------- windows


@dataclass
class _Surface:
    """The heights of one CRS group under the region, as a bilinear grid in CRS units."""

    to_source: object  # pyproj Transformer (lon, lat) -> CRS (x, y); None for EPSG:4326
    grid: Dtm  # elevation in the source's own coordinates (only its bilinear surface is used)
    paths: tuple[Path, ...]


def _to_source(to_source, lon: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if to_source is None:
        return lon, lat
    sx, sy = to_source.transform(lon, lat)
    return np.asarray(sx), np.asarray(sy)


def _outline_in_source(frame: LocalFrame, region: tuple[float, float, float, float],
                       to_source) -> tuple[float, float, float, float]:
    """Bounding box (CRS units) of the region's outline at the extreme terrain heights."""
    xmin, xmax, ymin, ymax = region
    t = np.linspace(0.0, 1.0, _OUTLINE_POINTS)
    xs = np.concatenate([xmin + (xmax - xmin) * t, np.full_like(t, xmax),
                         xmax - (xmax - xmin) * t, np.full_like(t, xmin)])
    ys = np.concatenate([np.full_like(t, ymin), ymin + (ymax - ymin) * t,
                         np.full_like(t, ymax), ymax - (ymax - ymin) * t])
    # World z of terrain at the extremes: ellipsoidal height minus the origin's, minus the
    # drop of the ground below the tangent plane at the far corner.
    reach = math.hypot(max(abs(xmin), abs(xmax)), max(abs(ymin), abs(ymax)))
    drop = reach**2 / (2 * 6.3e6)
    h0 = frame.origin.height_m
    points = []
    for z in (LOWEST_TERRAIN_M - h0 - drop, HIGHEST_TERRAIN_M - h0):
        lat, lon, _ = frame.world_to_geodetic(np.column_stack([xs, ys, np.full_like(xs, z)]))
        points.append(np.column_stack(_to_source(to_source, lon, lat)))
    pts = np.concatenate(points)
    if not np.all(np.isfinite(pts)):
        raise DtmError("the flight region does not map into the DEM's CRS (outside the "
                       "projection's domain); expected a DEM CRS valid over the flight")
    return float(pts[:, 0].min()), float(pts[:, 0].max()), float(pts[:, 1].min()), \
        float(pts[:, 1].max())


def _group_surface(group: list[DemSource], frame: LocalFrame,
                   region: tuple[float, float, float, float]) -> _Surface | None:
    """Read the window of one CRS group (files sharing a pixel grid), mosaicked."""
    import rasterio
    from pyproj import CRS, Transformer
    from rasterio.windows import Window

    first = group[0]
    a, c, e, f = first.transform
    crs = CRS.from_wkt(first.crs_wkt)
    # EPSG:4326 rasters (SRTM, Copernicus) are indexed by longitude and latitude directly.
    to_source = (None if crs.equals(CRS.from_epsg(4326), ignore_axis_order=True)
                 else Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True))
    bx0, bx1, by0, by1 = _outline_in_source(frame, region, to_source)
    # Column/row indices (of pixel centres) in the first file's grid.
    cols = sorted(((bx0 - c) / a - 0.5, (bx1 - c) / a - 0.5))
    rows = sorted(((by0 - f) / e - 0.5, (by1 - f) / e - 0.5))
    col_lo, col_hi = math.floor(cols[0]) - WINDOW_PAD_PX, math.ceil(cols[1]) + WINDOW_PAD_PX
    row_lo, row_hi = math.floor(rows[0]) - WINDOW_PAD_PX, math.ceil(rows[1]) + WINDOW_PAD_PX
    # Each file's offset in that grid; clip the window to the files' union.
    offsets = []
    for src in group:
        oc, orow = (src.transform[1] - c) / a, (src.transform[3] - f) / e
        if abs(oc - round(oc)) > 1e-6 or abs(orow - round(orow)) > 1e-6:
            raise _fail(src.path, f"its pixels are offset by ({oc % 1:.3f}, {orow % 1:.3f}) "
                        f"pixels from those of {first.path.name}",
                        "tiles of one CRS and pixel size on one pixel grid")
        offsets.append((round(oc), round(orow)))
    col_lo = max(col_lo, min(oc for oc, _ in offsets))
    col_hi = min(col_hi, max(oc + s.width - 1 for (oc, _), s in zip(offsets, group)))
    row_lo = max(row_lo, min(orow for _, orow in offsets))
    row_hi = min(row_hi, max(orow + s.height - 1 for (_, orow), s in zip(offsets, group)))
    if col_hi - col_lo < 1 or row_hi - row_lo < 1:
        return None
    mosaic = np.full((row_hi - row_lo + 1, col_hi - col_lo + 1), np.nan)
    used = []
    for (oc, orow), src in zip(offsets, group):
        c0, c1 = max(col_lo, oc), min(col_hi, oc + src.width - 1)
        r0, r1 = max(row_lo, orow), min(row_hi, orow + src.height - 1)
        if c1 < c0 or r1 < r0:
            continue
        with gdal_quiet() as notes:
            try:
                with rasterio.open(src.path) as ds:
                    band = ds.read(1, window=Window(c0 - oc, r0 - orow, c1 - c0 + 1,
                                                    r1 - r0 + 1), masked=True)
            except Exception as exc:
                raise _fail(src.path, "cannot read its pixels: the file is damaged or "
                            f"truncated ({gdal_reason(exc, notes)})", "a complete raster") \
                    from None
        heights = np.ma.filled(band.astype(np.float64) * src.scale + src.offset, np.nan)
        target = mosaic[r0 - row_lo:r1 - row_lo + 1, c0 - col_lo:c1 - col_lo + 1]
        empty = np.isnan(target)
        target[empty] = heights[empty]
        used.append(src.path)
    if mosaic.shape[0] < 2 or mosaic.shape[1] < 2 or np.isnan(mosaic).all():
        return None
    try:
        grid = Dtm(mosaic, c + (col_lo + 0.5) * a, f + (row_lo + 0.5) * e, a, e)
    except DtmError:
        return None  # no complete bilinear cell under the flight
    logger.info("DEM window %dx%d pixels from %s", mosaic.shape[1], mosaic.shape[0],
                ", ".join(p.name for p in used))
    return _Surface(to_source, grid, tuple(used))


def _surfaces(sources: list[DemSource], frame: LocalFrame,
              region: tuple[float, float, float, float]) -> list[_Surface]:
    groups: dict[tuple[str, float, float], list[DemSource]] = {}
    for src in sources:
        groups.setdefault((src.crs_wkt, src.transform[0], src.transform[2]), []).append(src)
    surfaces = [s for s in (_group_surface(g, frame, region) for g in groups.values()) if s]
    if not surfaces:
        names = ", ".join(str(s.path) for s in sources)
        lat, lon, _ = frame.world_to_geodetic(np.array(
            [[region[0], region[2], 0.0], [region[1], region[3], 0.0]]))
        raise DtmError(f"{names}: no data under the flight (latitude {lat.min():.4f} to "
                       f"{lat.max():.4f}, longitude {lon.min():.4f} to {lon.max():.4f}); "
                       "expected DEM tiles covering it")
    return surfaces


@dataclass(frozen=True)
class DemWindow:
    """The DEM under a region in the DEM's own coordinates (for plots in its CRS).

    Attributes:
        grid: heights as read (the file's vertical datum) on the file's pixel centres,
            x and y in CRS units (degrees for EPSG:4326).
        crs_wkt: the CRS of x and y.
        pixel_size_m: the finer pixel size in metres near the region.
        paths: the files it was read from.
    """

    grid: Dtm
    crs_wkt: str
    pixel_size_m: float
    paths: tuple[Path, ...]

    def to_crs(self, latitude_deg: np.ndarray, longitude_deg: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """CRS x, y (N,) of geodetic points."""
        from pyproj import CRS, Transformer

        crs = CRS.from_wkt(self.crs_wkt)
        if crs.equals(CRS.from_epsg(4326), ignore_axis_order=True):
            return np.asarray(longitude_deg, float), np.asarray(latitude_deg, float)
        x, y = Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True).transform(
            longitude_deg, latitude_deg)
        return np.asarray(x), np.asarray(y)


def read_dem_window(paths: Sequence[str | os.PathLike], frame: LocalFrame,
                    region_m: tuple[float, float, float, float], vertical_datum: VerticalDatum,
                    crs: str | None = None) -> DemWindow:
    """The first CRS group of DEM files under a world region, as stored (no resampling).

    Raises:
        DtmError: as :func:`import_dem`.
    """
    sources = read_dem_sources(paths, vertical_datum, crs)
    surface = _surfaces(sources, frame, tuple(float(v) for v in region_m))[0]  # type: ignore[arg-type]
    lat, _, _ = frame.world_to_geodetic(np.array([(region_m[0] + region_m[1]) / 2,
                                                  (region_m[2] + region_m[3]) / 2, 0.0]))
    first = next(s for s in sources if s.path == surface.paths[0])
    return DemWindow(surface.grid, first.crs_wkt, first.pixel_size_m(float(lat[0])),
                     surface.paths)


def _terrain_height(surfaces: list[_Surface], datum: VerticalDatum,
                    lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Ellipsoidal terrain height (N,) at geodetic points; NaN where no file has data."""
    height = np.full(lat.shape, np.nan)
    for surface in surfaces:
        need = np.isnan(height)
        if not need.any():
            break
        sx, sy = _to_source(surface.to_source, lon[need], lat[need])
        height[need] = surface.grid.height(sx, sy)
    valid = np.isfinite(height)
    if valid.any() and datum is not VerticalDatum.ELLIPSOID:
        height[valid] = ellipsoidal_height_m(datum, lat[valid], lon[valid], height[valid])
    return height


def _resample(frame: LocalFrame, surfaces: list[_Surface], datum: VerticalDatum,
              x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, int]:
    """World terrain z (N,) at world (x, y) nodes, and the count that did not converge."""
    z = np.full(x.shape, np.nan)
    active = np.arange(x.size)
    # Start on the ellipsoid's drop below the tangent plane (a sphere's is close enough).
    z_try = -(x**2 + y**2) / (2 * WGS84_A_M) - frame.origin.height_m
    for _ in range(MAX_ITERATIONS):
        lat, lon, h = frame.world_to_geodetic(
            np.column_stack([x[active], y[active], z_try[active]]))
        terrain = _terrain_height(surfaces, datum, lat, lon)
        has_data = np.isfinite(terrain)
        active, lat, lon, h, terrain = (active[has_data], lat[has_data], lon[has_data],
                                        h[has_data], terrain[has_data])
        step = (terrain - h) / frame.up_z(lat, lon)
        z_try[active] += step
        done = np.abs(step) <= CONVERGENCE_M
        z[active[done]] = z_try[active[done]]
        active = active[~done]
        if active.size == 0:
            break
    return z, int(active.size)


def _resampling_rms_m(dtm: Dtm, frame: LocalFrame, surfaces: list[_Surface],
                      datum: VerticalDatum) -> float:
    """RMS difference (m) between the world grid's bilinear surface and the DEM's own at
    ``RESAMPLING_CHECK_POINTS`` points drawn (seeded) over the grid."""
    xmin, xmax, ymin, ymax = dtm.bounds
    rng = np.random.default_rng(0)
    x = rng.uniform(xmin, xmax, RESAMPLING_CHECK_POINTS)
    y = rng.uniform(ymin, ymax, RESAMPLING_CHECK_POINTS)
    exact, _ = _resample(frame, surfaces, datum, x, y)
    diff = dtm.height(x, y) - exact
    diff = diff[np.isfinite(diff)]
    return float(np.sqrt(np.mean(diff**2))) if diff.size else 0.0


def import_dem(paths: Sequence[str | os.PathLike], frame: LocalFrame,
               region_m: tuple[float, float, float, float], vertical_datum: VerticalDatum,
               *, crs: str | None = None, spacing_m: float | None = None,
               sigma_h_m: float | None = None) -> Dtm:
    """Read the DEM under a world region and resample it into a world-frame :class:`Dtm`.

    See the module docstring for the method.

    Args:
        paths: DEM files, the first listed wins where they overlap.
        frame: the log's local frame (world = ENU at its origin).
        region_m: (xmin, xmax, ymin, ymax) world region to cover (m).
        vertical_datum: what the files' heights are measured from.
        crs: CRS of files that carry none (``dtm.crs``).
        spacing_m: world grid spacing (m); None: ``SPACING_PER_PIXEL`` times the finest
            source pixel size in metres.
        sigma_h_m: the DEM's 1-sigma height error; None: the Fig. 6 model at the DEM's
            pixel size (:func:`~cdtm_graph.dtm.sigma_h_from_grid_spacing`).

    Returns:
        The world DTM: heights are world z (so the ground curves away below the plane).
        Its ``sigma_h_m`` is the DEM's combined with the resampling error measured at
        ``RESAMPLING_CHECK_POINTS`` points (root sum of squares).

    Raises:
        DtmError: unreadable files, no CRS, no data under the region.
    """
    sources = read_dem_sources(paths, vertical_datum, crs)
    xmin, xmax, ymin, ymax = (float(v) for v in region_m)
    if not (xmin < xmax and ymin < ymax) or not all(map(math.isfinite, region_m)):
        raise DtmError(f"DEM region {region_m!r}; expected finite xmin < xmax, ymin < ymax")
    surfaces = _surfaces(sources, frame, (xmin, xmax, ymin, ymax))
    lat_c, _, _ = frame.world_to_geodetic(np.array([(xmin + xmax) / 2, (ymin + ymax) / 2,
                                                    0.0]))
    used = {p for sf in surfaces for p in sf.paths}
    pixel_m = min(s.pixel_size_m(float(lat_c[0])) for s in sources if s.path in used)
    if spacing_m is None:
        spacing_m = SPACING_PER_PIXEL * pixel_m
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise DtmError(f"DEM grid spacing {spacing_m!r} m; expected a finite value > 0")
    i0, i1 = math.floor(xmin / spacing_m), math.ceil(xmax / spacing_m)
    j0, j1 = math.floor(ymin / spacing_m), math.ceil(ymax / spacing_m)
    cols, rows = i1 - i0 + 1, j1 - j0 + 1
    if cols * rows > MAX_GRID_NODES:
        names = ", ".join(str(s.path) for s in sources)
        raise DtmError(
            f"{names}: the world grid would be {cols} x {rows} = {cols * rows:.3g} nodes "
            f"({8e-9 * cols * rows:.3g} GB) at a spacing of {spacing_m:g} m over "
            f"{(xmax - xmin) / 1e3:.4g} x {(ymax - ymin) / 1e3:.4g} km (the prior track plus "
            f"dtm.margin_m); expected at most {MAX_GRID_NODES:.3g} nodes: a larger "
            "dtm.spacing_m or a smaller dtm.margin_m in flight.yaml")
    xs = (i0 + np.arange(cols)) * spacing_m
    try:
        elevation = np.full((rows, cols), np.nan)
    except MemoryError:
        names = ", ".join(str(s.path) for s in sources)
        raise DtmError(
            f"{names}: the world grid of {cols} x {rows} nodes at {spacing_m:g} m "
            f"({8e-9 * cols * rows:.3g} GB) does not fit in memory; expected a larger "
            "dtm.spacing_m or a smaller dtm.margin_m in flight.yaml") from None
    rows_per_chunk = max(1, CHUNK_NODES // cols)
    unconverged = 0
    for r0 in range(0, rows, rows_per_chunk):
        r1 = min(rows, r0 + rows_per_chunk)
        ys = (j0 + np.arange(r0, r1)) * spacing_m
        gx, gy = np.meshgrid(xs, ys)
        z, bad = _resample(frame, surfaces, vertical_datum, gx.ravel(), gy.ravel())
        elevation[r0:r1] = z.reshape(r1 - r0, cols)
        unconverged += bad
    if unconverged:
        logger.warning("DEM import: %d nodes did not converge within %d steps (steep terrain "
                       "far from the origin); they are no data", unconverged, MAX_ITERATIONS)
    covered = float(np.isfinite(elevation).mean())
    try:
        dtm = Dtm(elevation, xs[0], j0 * spacing_m, spacing_m, spacing_m)
        # The DEM's own error follows its own pixel size (Fig. 6 model), not the finer
        # world grid's; the resampling adds its own, measured here.
        resampling_m = _resampling_rms_m(dtm, frame, surfaces, vertical_datum)
        dem_sigma = sigma_h_m if sigma_h_m is not None else sigma_h_from_grid_spacing(pixel_m)
        logger.info("DEM resampled into a %dx%d world grid at %.2f m (%.1f%% with data); "
                    "resampling error %.3f m rms, sigma_h %.3f m -> %.3f m", cols, rows,
                    spacing_m, 100 * covered, resampling_m, dem_sigma,
                    math.hypot(dem_sigma, resampling_m))
        dtm.sigma_h_m = math.hypot(dem_sigma, resampling_m)
        return dtm
    except DtmError as exc:
        names = ", ".join(str(s.path) for s in sources)
        raise DtmError(f"{names}: {exc}") from None
