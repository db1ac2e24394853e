"""Ray-casting speed of :meth:`cdtm_graph.dtm.Dtm.raycast` on one core.

Scenario (the task's target: >= 1e6 rays/s): a 1000x1000 fractal DTM (3 m spacing,
~3x3 km, 300 m relief) and downward camera rays, 60 deg field of view, from 1000 m
above the mean terrain, camera positions spread over the interior of the map.

Run ``python benchmarks/bench_raycast.py``; it prints ``rays_per_s=...``.
``measure_rays_per_s()`` returns the number for ``benchmarks/bench_core.py``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

try:
    import cdtm_graph  # noqa: F401
except ImportError:  # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cdtm_graph.dtm import Dtm, RayStatus  # noqa: E402
from cdtm_graph.sim.terrain import fractal_terrain  # noqa: E402

GRID_SAMPLES = 1000
SPACING_M = 3.0
ALTITUDE_M = 1000.0
FOV_DEG = 60.0
TILT_SIGMA = 0.05  # rad, random attitude of the camera about nadir


def make_scenario(n_rays: int, seed: int = 0) -> tuple[Dtm, np.ndarray, np.ndarray]:
    """The benchmark DTM and (n_rays, 3) origins and directions (world frame)."""
    dtm = fractal_terrain(size_m=(GRID_SAMPLES - 1) * SPACING_M, spacing_m=SPACING_M, seed=seed)
    rng = np.random.default_rng(seed)
    xmin, xmax, ymin, ymax = dtm.bounds
    half = np.tan(np.radians(FOV_DEG / 2))
    # Keep every ray's footprint (incl. tilt, down to the lowest terrain) inside the map.
    margin_m = 1.2 * ALTITUDE_M * (half + 4 * TILT_SIGMA) * np.sqrt(2)
    n_cams = max(1, n_rays // 1000)
    cams = np.column_stack(
        [
            rng.uniform(xmin + margin_m, xmax - margin_m, n_cams),
            rng.uniform(ymin + margin_m, ymax - margin_m, n_cams),
            np.full(n_cams, ALTITUDE_M),
        ]
    )
    origins = cams[rng.integers(0, n_cams, n_rays)]
    # Pixels uniform over a square image of the given FOV, camera looking straight down
    # with a small random tilt, as a nadir camera on an aircraft.
    directions = np.column_stack(
        [rng.uniform(-half, half, n_rays), rng.uniform(-half, half, n_rays), -np.ones(n_rays)]
    )
    directions[:, :2] += rng.normal(0.0, TILT_SIGMA, (n_rays, 2))
    return dtm, origins, directions


def measure_rays_per_s(n_rays: int = 1_000_000, repeats: int = 3) -> float:
    """Best-of-``repeats`` rays per second of ``Dtm.raycast`` (after a compile warm-up)."""
    dtm, origins, directions = make_scenario(n_rays)
    dtm.raycast(origins[:100], directions[:100])  # numba compile / cache load
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        hits = dtm.raycast(origins, directions)
        best = min(best, time.perf_counter() - start)
    if np.mean(hits.status == RayStatus.HIT) < 0.999:
        raise RuntimeError("benchmark rays should (nearly) all hit the terrain")
    return n_rays / best


if __name__ == "__main__":
    print(f"rays_per_s={measure_rays_per_s():.0f}")
