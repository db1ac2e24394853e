"""DEM import speed and memory: a 60 x 12 km flight region out of a 3601 x 3601 SRTM-sized tile.

Writes an EPSG:4326, 1" int16 tile (N36E127, smooth random relief) to a temporary
directory, then imports the region with EGM96 heights at the default spacing (half the
pixel, ~12.4 m) in a fresh process. Run: ``python benchmarks/bench_dem.py``. Ends with
one line: ``nodes=N import_s=T us_per_node=U peak_rss_mb=M``.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

_CHILD = textwrap.dedent("""
    import resource, sys, time
    sys.path.insert(0, sys.argv[2])
    from cdtm_graph.dem import import_dem
    from cdtm_graph.geodesy import GeodeticOrigin, LocalFrame, VerticalDatum
    frame = LocalFrame(GeodeticOrigin(36.3, 127.2, 100.0))
    t0 = time.perf_counter()
    dtm = import_dem([sys.argv[1]], frame, (-5000.0, 55000.0, -6000.0, 6000.0),
                     VerticalDatum.EGM96)
    elapsed = time.perf_counter() - t0
    nodes = dtm.elevation.size
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"nodes={nodes} import_s={elapsed:.2f} us_per_node={1e6 * elapsed / nodes:.2f} "
          f"peak_rss_mb={peak_mb:.0f}")
""")


def _tile(path: Path) -> None:
    import rasterio
    from affine import Affine

    rng = np.random.default_rng(1)
    # Smooth relief: a few hundred random sinusoids, 2-20 km wavelengths, 600 m range.
    lon = 127.0 + np.arange(3601) / 3600.0
    lat = 37.0 - np.arange(3601) / 3600.0
    heights = np.full((3601, 3601), 400.0)
    for _ in range(40):
        k = rng.uniform(5.0, 50.0, 2) * rng.choice([-1, 1], 2)
        phase = rng.uniform(0, 2 * np.pi)
        heights += 15.0 * np.sin(k[0] * lon[None, :] + k[1] * lat[:, None] + phase)
    pixel = 1.0 / 3600.0
    with rasterio.open(path, "w", driver="GTiff", width=3601, height=3601, count=1,
                       dtype="int16", crs="EPSG:4326",
                       transform=Affine(pixel, 0.0, 127.0 - pixel / 2, 0.0, -pixel,
                                        37.0 + pixel / 2)) as dst:
        dst.write(heights.astype(np.int16), 1)


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        tile = Path(tmp) / "N36E127.tif"
        _tile(tile)
        out = subprocess.run([sys.executable, "-c", _CHILD, str(tile), str(ROOT)], check=True,
                             capture_output=True, text=True)
        print(out.stdout.strip())


if __name__ == "__main__":
    main()
