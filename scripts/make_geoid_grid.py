"""Build ``cdtm_graph/data/geoid/egm96_15.tif``, the EGM96 grid, from PROJ's ``egm96_15.gtx``.

Source: Debian's ``proj-data`` package (9.1.1-1) ships ``/usr/share/proj/egm96_15.gtx``, NGA's
EGM96 15-minute geoid-height grid (WW15MGH) in PROJ's GTX format: 721 x 1440 big-endian
float32 values, south row first, a sample on every quarter degree from -90 to 90 latitude
and -180 to 179.75 longitude. Get it without installing anything::

    apt-get download proj-data && dpkg-deb -x proj-data_*_all.deb proj-data
    python scripts/make_geoid_grid.py proj-data/usr/share/proj/egm96_15.gtx

The output is a GeoTIFF that PROJ reads as a ``vgridshift`` grid (and rasterio as a raster):
EPSG:4326, north row first, pixel-is-point, int16 heights in units of 1/256 m (the scale
is in the file's metadata; quantization error <= 1/512 m ~ 2 mm), DEFLATE with horizontal
differencing: 1.1 MB instead of 4.2 MB.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

#: GTX header: four big-endian doubles (south latitude, west longitude, dlat, dlon) and
#: two big-endian int32 (rows, columns).
_GTX_HEADER_BYTES = 40
#: Heights are stored as round(N * SCALE) in int16; |N| < 108 m fits (108 * 256 < 32767).
SCALE = 256
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "cdtm_graph" / "data" / "geoid" / "egm96_15.tif"


def read_gtx(path: Path) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The GTX grid, south row first, and (south lat, west lon, dlat, dlon) in degrees."""
    raw = path.read_bytes()
    south, west, dlat, dlon = np.frombuffer(raw[:32], dtype=">f8").tolist()
    rows, cols = np.frombuffer(raw[32:40], dtype=">i4").tolist()
    grid = np.frombuffer(raw[_GTX_HEADER_BYTES:], dtype=">f4").reshape(rows, cols)
    return grid.astype(np.float64), (south, west, dlat, dlon)


def write_grid(grid_south_first: np.ndarray, header: tuple[float, float, float, float],
               out: Path) -> float:
    """Write the GeoTIFF; returns the largest quantization error (m)."""
    import rasterio
    from rasterio.transform import from_origin

    south, west, dlat, dlon = header
    north_first = grid_south_first[::-1]
    rows, cols = north_first.shape
    quantized = np.round(north_first * SCALE).astype(np.int16)
    north = south + (rows - 1) * dlat
    out.parent.mkdir(parents=True, exist_ok=True)
    profile = {
        "driver": "GTiff", "width": cols, "height": rows, "count": 1, "dtype": "int16",
        "crs": "EPSG:4326",
        # Samples sit on the quarter degrees: the pixel (area) corner is half a cell off.
        "transform": from_origin(west - dlon / 2, north + dlat / 2, dlon, dlat),
        "compress": "deflate", "predictor": 2, "zlevel": 9,
        "tiled": True, "blockxsize": 512, "blockysize": 512,
    }
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(quantized, 1)
        dst.scales = (1.0 / SCALE,)
        dst.offsets = (0.0,)
        dst.update_tags(AREA_OR_POINT="Point")
        dst.update_tags(1, TYPE="GEOID_UNDULATION", UNIT="metre",
                        SOURCE="NGA EGM96 15' grid (WW15MGH) via PROJ egm96_15.gtx")
        dst.set_band_description(1, "geoid_undulation")
    return float(np.abs(quantized / SCALE - north_first).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("gtx", type=Path, help="egm96_15.gtx from Debian's proj-data")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    grid, header = read_gtx(args.gtx)
    worst = write_grid(grid, header, args.out)
    print(f"{args.out}: {grid.shape[0]}x{grid.shape[1]} samples, "
          f"{args.out.stat().st_size / 1e6:.2f} MB, quantization error <= {worst * 1e3:.2f} mm")


if __name__ == "__main__":
    main()
